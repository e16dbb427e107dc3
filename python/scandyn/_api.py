"""The Python API over the extension module: models, engines, and the function API.

Everything numeric happens in the library's engines (scandyn/engine.hpp) through
scandyn._scandyn; this file only resolves names, allocates results and caches
engines. Arrays go to the engines as they are (their own strides, no copy); the
extension module checks shapes, dtypes, devices and aliasing (python/src/module.cpp).
"""

import os

import numpy as np

from . import _scandyn as _ext
from . import models as _models
from .errors import DeviceError, DTypeError, ForwardDynamicsError, ShapeError

Status = _ext.Status

_FLOAT_NAMES = ("float32", "float64")
_KDL_CPU = 1  # DLPack device types that are host memory: CPU, CUDA pinned host
_KDL_CUDA_HOST = 3


# ---- models -------------------------------------------------------------------------


class Model:
    """A loaded model (immutable). Bodies are in DoF order (``parents[i] < i``), the order
    ``scandyn info`` prints. Made by :func:`load_model`."""

    __slots__ = ("_m", "_engines", "__weakref__")

    def __init__(self, ext_model):
        self._m = ext_model
        self._engines = {}  # the function API's engines: (algo, backend, dtype, option) -> engine

    nv = property(lambda self: self._m.nv, doc="degrees of freedom: entries of qd, qdd, tau")
    nq = property(lambda self: self._m.nq, doc="entries of q (nv + 1 per quaternion: floating base, ball joints)")
    floating_base = property(lambda self: self._m.floating_base, doc="True when body 0 is a free joint")
    name = property(lambda self: self._m.name, doc="robot name (URDF) or generator spec")
    source = property(lambda self: self._m.source, doc="file path or generator spec it was loaded from")
    root_link = property(lambda self: self._m.root_link, doc="the URDF root link (the fixed base)")
    joint_names = property(lambda self: self._m.joint_names, doc="(bodies) joint of each body")
    link_names = property(lambda self: self._m.link_names, doc="(bodies) URDF child link of each joint")
    parents = property(lambda self: self._m.parents, doc="(bodies) parent body of each body, -1 for the base")
    joint_types = property(lambda self: self._m.joint_types,
                           doc="(bodies) 'revolute', 'prismatic', 'spherical' or 'free'")
    q_lower = property(lambda self: np.array(self._m.q_lower), doc="(bodies) lower position limits (-inf: none)")
    q_upper = property(lambda self: np.array(self._m.q_upper), doc="(bodies) upper position limits (+inf: none)")
    gravity = property(lambda self: np.array(self._m.gravity), doc="gravity in the base frame (m/s^2)")
    frames = property(lambda self: self._m.frames,
                      doc="every frame's name: the URDF links, fixed ones included (scandyn.kinematics)")

    def clear_cache(self):
        """Drops the engines (and their scratch memory) the function API made for this model."""
        self._engines.clear()

    def __repr__(self):
        return f"scandyn.Model(name={self.name!r}, nv={self.nv}, source={self.source!r})"


def load_model(spec, allow_nonphysical_inertia=False, floating_base=False):
    """Loads a model: a generator spec ("rope:1000", "ballrope:N", "chain:N",
    "tree:N:SEED", "curtain:K:N"), a URDF path, or the name of a model in
    $SCANDYN_MODELS_DIR or shipped with the package ("iiwa", "hyq", "atlas";
    scandyn.models). floating_base=True gives the root link a free joint: q (nq = nv + 1)
    starts [px, py, pz, qx, qy, qz, qw], qd/qdd/tau [base twist (w, v) in the base frame /
    base wrench (n, f)]. Raises ModelError with the library's message (missing file,
    malformed URDF, non-physical inertia unless allow_nonphysical_inertia=True, a
    floating base on a root that is the world frame or has no mass, ...)."""
    return Model(_ext.load_model(resolve_model_spec(spec), allow_nonphysical_inertia, floating_base))


def resolve_model_spec(spec):
    """The spec load_model loads: a generator spec as it is; a model file by the library's
    lookup (the path as given, $SCANDYN_MODELS_DIR, the source tree's models/), then among
    the models installed inside this package (".urdf" optional); else the spec unchanged
    (the library's "not found" names where it looked)."""
    spec = os.fspath(spec)
    if _ext.is_generator_spec(spec):
        return spec
    found = _ext.find_model_file(spec)
    if os.path.isfile(found):
        return found
    if not os.path.isabs(spec):
        for cand in (spec, spec + ".urdf"):
            p = os.path.join(_models.directory(), cand)
            if os.path.isfile(p):
                return p
    return spec


# ---- arrays -------------------------------------------------------------------------


def _is_torch(x):
    return type(x).__module__.startswith("torch")


def _dtype_name(x):
    """'float32', 'float64', or another dtype's name, of an array-like's dtype."""
    d = getattr(x, "dtype", None)
    if d is None:
        return None
    if _is_torch(x):
        return str(d).replace("torch.", "")
    try:
        return np.dtype(d).name
    except TypeError:
        return str(d)


def _normalize_dtype(dtype):
    try:
        name = np.dtype(dtype).name
    except TypeError:
        name = str(dtype).replace("torch.", "")
    if name not in _FLOAT_NAMES:
        raise DTypeError(f"dtype must be float32 or float64, got {dtype!r}")
    return name


def _check_host(x, name):
    """Raises DeviceError for an array on a CUDA (or any non-host) device: nothing is ever
    copied to the host behind the caller's back."""
    if hasattr(x, "__cuda_array_interface__"):
        raise DeviceError(
            f"{name} is a CUDA array: backend 'cuda' from Python is not implemented yet; "
            "pass host (NumPy / CPU) arrays"
        )
    dev = getattr(x, "__dlpack_device__", None)
    if dev is not None and not isinstance(x, np.ndarray):
        kind = dev()[0]
        if int(kind) not in (_KDL_CPU, _KDL_CUDA_HOST):
            raise DeviceError(
                f"{name} is on DLPack device type {int(kind)} (not host memory): backend 'cuda' "
                "from Python is not implemented yet; pass host (NumPy / CPU) arrays"
            )


def _inputs(named, dtype=None):
    """The call's arrays, as given (no copy), after the device check; Python lists,
    tuples and scalars (not arrays) become NumPy arrays of the call's dtype. Returns
    (arrays, dtype name of the first array)."""
    first = dtype
    for name, x in named:
        if x is not None and not isinstance(x, (list, tuple, int, float)):
            _check_host(x, name)
            if first is None:
                first = _dtype_name(x)
    first = first or "float64"
    out = []
    for name, x in named:
        if isinstance(x, (list, tuple, int, float)):
            x = np.asarray(x, dtype=first if first in _FLOAT_NAMES else "float64")
        out.append(x)
    return out, first


def _lead_of(q, name="q"):
    shape = tuple(getattr(q, "shape", ()))
    if len(shape) not in (1, 2):
        raise ShapeError(f"{name} has shape {shape}, expected (nq,) or (B, nq)")
    return shape[:-1]


def _empty(like, shape, dtype):
    if _is_torch(like):
        import torch

        return torch.empty(shape, dtype=getattr(torch, dtype))
    return np.empty(shape, dtype=dtype)


def _check_out(out):
    if isinstance(out, (list, tuple)) or getattr(out, "shape", None) is None:
        raise DTypeError(f"out must be an array (NumPy or DLPack), got {type(out).__name__}")
    _check_host(out, "out")
    if isinstance(out, np.ndarray) and not out.flags.writeable:
        raise ShapeError("out is read-only")


def _call(fn, *args, **kw):
    try:
        return fn(*args, **kw)
    except TypeError as e:
        if "incompatible function arguments" not in str(e):
            raise
        raise DTypeError(
            "cannot read the arrays of this call without a copy: each must be a float32 or "
            "float64 array in host memory (buffer protocol or DLPack) whose strides are "
            "multiples of its item size, and out must be writable"
        ) from e


# ---- engines ------------------------------------------------------------------------


def _resolve_backend(backend):
    if backend == "auto":
        return "openmp" if not _ext.backend_unusable("openmp") else "serial"
    return backend


class _EngineBase:
    _ext_class = None

    def __init__(self, model, backend, max_batch, dtype, **options):
        if not isinstance(model, Model):
            raise TypeError(f"model must be a scandyn.Model (scandyn.load_model), got {type(model).__name__}")
        self.model = model
        self._dtype = _normalize_dtype(dtype)
        self._e = self._ext_class(model._m, self._dtype, _resolve_backend(backend), int(max_batch), **options)

    backend = property(lambda self: self._e.backend, doc="'serial', 'openmp' or 'cuda'")
    strategy = property(lambda self: self._e.strategy, doc="the variant the engine runs")
    exact = property(lambda self: self._e.exact, doc="bit-identical to the serial reference")
    max_batch = property(lambda self: self._e.max_batch)
    nv = property(lambda self: self._e.nv)
    dtype = property(lambda self: np.dtype(self._dtype))

    def _prepare(self, named, out, tail=()):
        arrays, _ = _inputs(named, self._dtype)
        if out is None:
            lead = _lead_of(arrays[0])
            out = _empty(arrays[0], lead + (self.nv,) + tail, self._dtype)
        else:
            _check_out(out)
        return arrays, out

    def __repr__(self):
        return (
            f"scandyn.{type(self).__name__}(model={self.model.name!r}, backend={self.backend!r}, "
            f"strategy={self.strategy!r}, dtype={self._dtype}, max_batch={self.max_batch})"
        )


class InverseDynamics(_EngineBase):
    """tau = ID(q, qd, qdd, fext): RNEA with gravity, for up to max_batch instances.
    ``strategy``: 'auto', 'recursion', 'scan-local', 'scan-world' (CPU)."""

    _ext_class = _ext.InverseDynamics

    def __init__(self, model, backend="auto", max_batch=1, dtype=np.float64, strategy="auto", threads=0):
        super().__init__(model, backend, max_batch, dtype, strategy=strategy, threads=threads)

    def __call__(self, q, qd, qdd, fext=None, out=None):
        (q, qd, qdd, fext), out = self._prepare([("q", q), ("qd", qd), ("qdd", qdd), ("fext", fext)], out)
        _call(self._e.compute, q, qd, qdd, out, fext)
        return out


class BiasForces(_EngineBase):
    """h = RNEA(q, qd, 0, fext): Coriolis, centrifugal and gravity forces."""

    _ext_class = _ext.BiasForces

    def __init__(self, model, backend="auto", max_batch=1, dtype=np.float64, strategy="auto", threads=0):
        super().__init__(model, backend, max_batch, dtype, strategy=strategy, threads=threads)

    def __call__(self, q, qd, fext=None, out=None):
        (q, qd, fext), out = self._prepare([("q", q), ("qd", qd), ("fext", fext)], out)
        _call(self._e.compute, q, qd, out, fext)
        return out


class MassMatrix(_EngineBase):
    """M(q) by the CRBA: (B, nv, nv) (or (nv, nv) for one state), both triangles written."""

    _ext_class = _ext.MassMatrix

    def __init__(self, model, backend="auto", max_batch=1, dtype=np.float64, threads=0):
        super().__init__(model, backend, max_batch, dtype, threads=threads)

    def __call__(self, q, out=None):
        (q,), out = self._prepare([("q", q)], out, tail=(self.nv,))
        _call(self._e.compute, q, out)
        return out


class ForwardDynamics(_EngineBase):
    """qdd = FD(q, qd, tau, fext). ``method``: 'auto', 'aba', 'jsi', 'parallel' (chains),
    'hybrid' (cuda). An instance whose pivot is not positive and finite raises
    ForwardDynamicsError (its ``status`` says which; those instances' entries of out are
    left unwritten); ``last_status`` is the last call's scandyn.Status."""

    _ext_class = _ext.ForwardDynamics

    def __init__(self, model, backend="auto", max_batch=1, dtype=np.float64, method="auto",
                 fallback_aba=False, threads=0):
        super().__init__(model, backend, max_batch, dtype, method=method, fallback_aba=fallback_aba,
                         threads=threads)
        self.last_status = None

    method = property(lambda self: self._e.method, doc="the method run ('auto' resolved)")

    def __call__(self, q, qd, tau, fext=None, out=None):
        (q, qd, tau, fext), out = self._prepare([("q", q), ("qd", qd), ("tau", tau), ("fext", fext)], out)
        status = _call(self._e.compute, q, qd, tau, out, fext)
        self.last_status = status
        if not status.ok:
            raise ForwardDynamicsError(f"forward dynamics failed: {status.message}", status)
        return out


# ---- the function API: engines cached per model ------------------------------------


def _cached(cls, key_option, model, backend, first, **options):
    if not isinstance(model, Model):
        raise TypeError(f"model must be a scandyn.Model (scandyn.load_model), got {type(model).__name__}")
    dtype = _dtype_name(first)
    if dtype not in _FLOAT_NAMES:
        raise DTypeError(f"q has dtype {dtype}, expected float32 or float64")
    lead = _lead_of(first)
    batch = lead[0] if lead else 1
    backend = _resolve_backend(backend)
    key = (cls.__name__, backend, dtype, key_option)
    engine = model._engines.get(key)
    if engine is None or engine.max_batch < batch:
        engine = cls(model, backend=backend, max_batch=max(batch, 1), dtype=dtype, **options)
        model._engines[key] = engine
    return engine


def inverse_dynamics(model, q, qd, qdd, fext=None, backend="auto", out=None):
    """tau = ID(q, qd, qdd, fext), gravity included. q, qd, qdd: (B, nv) or (nv,);
    fext: optional (B, nv, 6) body wrenches [moment; force] in body frames. Returns tau
    (out when given)."""
    (q, qd, qdd, fext), _ = _inputs([("q", q), ("qd", qd), ("qdd", qdd), ("fext", fext)])
    return _cached(InverseDynamics, None, model, backend, q)(q, qd, qdd, fext=fext, out=out)


def bias_forces(model, q, qd, fext=None, backend="auto", out=None):
    """h = RNEA(q, qd, 0, fext): (B, nv) or (nv,)."""
    (q, qd, fext), _ = _inputs([("q", q), ("qd", qd), ("fext", fext)])
    return _cached(BiasForces, None, model, backend, q)(q, qd, fext=fext, out=out)


def mass_matrix(model, q, backend="auto", out=None):
    """M(q): (B, nv, nv), or (nv, nv) for q of shape (nv,)."""
    (q,), _ = _inputs([("q", q)])
    return _cached(MassMatrix, None, model, backend, q)(q, out=out)


def forward_dynamics(model, q, qd, tau, fext=None, method="auto", backend="auto", out=None):
    """qdd = FD(q, qd, tau, fext), gravity included: (B, nv) or (nv,). Raises
    ForwardDynamicsError (with .status) when an instance's pivot is not positive."""
    (q, qd, tau, fext), _ = _inputs([("q", q), ("qd", qd), ("tau", tau), ("fext", fext)])
    engine = _cached(ForwardDynamics, method, model, backend, q, method=method)
    return engine(q, qd, tau, fext=fext, out=out)
