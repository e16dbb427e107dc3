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
_MAX_INDEX = 2**31 - 1  # scandyn::Index is a 32-bit int


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
#
# Where a call's arrays live decides the path: host memory (NumPy, torch CPU, JAX CPU,
# any buffer-protocol or DLPack producer) goes to the engine's compute(); CUDA memory
# (torch CUDA tensors, CuPy, JAX on a GPU, any DLPack producer with device type CUDA)
# to the CUDA engine's compute_async() on the caller's stream (the extension checks
# that every array is on the same device). CUDA arrays are handed over as DLPack
# capsules made without synchronisation (torch.utils.dlpack.to_dlpack, CuPy's
# toDlpack); JAX arrays through __dlpack__(stream=...), which makes that stream wait
# until JAX has produced them.

_KDL_CPU, _KDL_CUDA, _KDL_CUDA_HOST = 1, 2, 3
_LEGACY_STREAM = 1  # DLPack's and CUDA's name for the legacy default stream (cudaStreamLegacy)


_KINDS = {np.ndarray: "numpy"}  # type -> array library, filled as types are seen


def _kind(x):
    """The array library of x: 'numpy', 'torch', 'cupy', 'jax' or 'other'."""
    t = type(x)
    kind = _KINDS.get(t)
    if kind is None:
        mod = t.__module__
        kind = ("numpy" if isinstance(x, np.ndarray) else "torch" if mod.startswith("torch")
                else "cupy" if mod.startswith("cupy") else "jax" if mod.startswith(("jax", "jaxlib")) else "other")
        _KINDS[t] = kind
        if kind == "torch":
            _DIRECT_IN[t] = _DIRECT_OUT[t] = _torch_capsule
    return kind


class _Torch:
    """torch's functions the device path calls on every call, looked up once."""

    raw_stream = None  # torch._C._cuda_getCurrentRawStream, or a slower equivalent
    to_dlpack = None
    dtypes = None  # {"float32": torch.float32, "float64": torch.float64}

    @classmethod
    def load(cls):
        import torch
        import torch.utils.dlpack

        raw = getattr(torch._C, "_cuda_getCurrentRawStream", None)
        cls.raw_stream = raw if raw is not None else (lambda d: torch.cuda.current_stream(d).cuda_stream)
        cls.to_dlpack = torch.utils.dlpack.to_dlpack
        cls.dtypes = {"float32": torch.float32, "float64": torch.float64, "int32": torch.int32}
        return cls


def _is_torch(x):
    return _kind(x) == "torch"


def _cuda_device(x, kind, name):
    """The CUDA ordinal of an array in CUDA device memory, None for host memory. Raises
    DeviceError for any other device and for arrays that offer only
    __cuda_array_interface__ (which names no device and no DLPack capsule)."""
    if kind == "numpy":
        return None
    if kind == "torch":
        return x.get_device() if x.is_cuda else None
    dev = getattr(x, "__dlpack_device__", None)
    if dev is None:
        if hasattr(x, "__cuda_array_interface__"):
            raise DeviceError(
                f"{name} offers only __cuda_array_interface__: scandyn reads CUDA arrays through "
                "DLPack (torch, CuPy, JAX, ...); wrap it with cupy.asarray or torch.as_tensor (no copy)"
            )
        return None
    kind_code, ordinal = dev()
    kind_code = int(kind_code)
    if kind_code in (_KDL_CPU, _KDL_CUDA_HOST):
        return None
    if kind_code == _KDL_CUDA:
        return int(ordinal)
    raise DeviceError(
        f"{name} is on DLPack device type {kind_code}: scandyn takes host memory or CUDA device memory"
    )


def _stream_handle(stream):
    """A cudaStream_t as an integer: an int, a torch.cuda.Stream (.cuda_stream) or a CuPy
    stream (.ptr)."""
    if isinstance(stream, (int, np.integer)):
        return int(stream)
    for attr in ("cuda_stream", "ptr"):
        v = getattr(stream, attr, None)
        if isinstance(v, int):
            return v
    raise TypeError(f"stream must be an int (a cudaStream_t), a torch.cuda.Stream or a CuPy stream, "
                    f"got {type(stream).__name__}")


def _current_stream(kind, device):
    """The stream the caller's library queues work on now: torch's and CuPy's current
    stream of the device; the legacy default stream for JAX (which exposes none) and
    others."""
    if kind == "torch":
        return (_Torch.raw_stream or _Torch.load().raw_stream)(device)
    if kind == "cupy":
        import cupy

        with cupy.cuda.Device(device):
            return cupy.cuda.get_current_stream().ptr
    return _LEGACY_STREAM


class _Where:
    """Where a call runs: host memory (cuda is None) or a CUDA ordinal, the array
    library of its first array, and the stream (CUDA)."""

    __slots__ = ("cuda", "kind", "stream", "like")

    def __init__(self, cuda, kind, stream, like):
        self.cuda, self.kind, self.stream, self.like = cuda, kind, stream, like


def _where(first, stream=None):
    kind = _kind(first)
    cuda = _cuda_device(first, kind, "q")
    s = None
    if cuda is not None:
        s = _stream_handle(stream) if stream is not None else _current_stream(kind, cuda)
    elif stream is not None:
        _stream_handle(stream)  # checked, unused on the host
    return _Where(cuda, kind, s, first)


def _handover(x, name, where):
    """An array as the extension reads it: torch tensors (host or CUDA) as a DLPack
    capsule from torch.utils.dlpack.to_dlpack, which synchronises nothing (and is
    quicker than torch's __dlpack__); CuPy arrays as toDlpack() capsules; JAX arrays
    on a GPU through __dlpack__(stream=...), which makes the call's stream wait for the
    array; everything else as it is. Arrays on another device than the first are
    passed on too, for the extension to name in its DeviceError."""
    if x is None:
        return x
    kind = _kind(x)
    if kind == "torch":
        return _torch_capsule(x)
    if where.cuda is None:
        return x
    if kind == "cupy":
        return x.toDlpack()
    if kind == "jax" and _cuda_device(x, kind, name) is not None:
        return x.__dlpack__(stream=where.stream)
    return x


def _torch_capsule(x):
    """A torch tensor's DLPack capsule (torch.utils.dlpack.to_dlpack: no synchronisation).
    The engines compute no gradients: a tensor that requires one is read as it is (the
    memory of its detached view); a torch that refuses to export it gets the detached view."""
    to_dlpack = _Torch.to_dlpack or _Torch.load().to_dlpack
    try:
        return to_dlpack(x)
    except RuntimeError:
        return to_dlpack(x.detach())


def _numpy_out(x):
    if not x.flags.writeable:
        raise ShapeError("out is read-only")
    return x


def _as_is(x):
    return x


# The call path's per-type handover for the common calls (arrays and out all torch
# tensors, or all NumPy arrays; fext may be None): type -> the array as the extension
# reads it, whatever its device. torch types are added as they are seen (_kind). Any
# other type (CuPy, JAX, lists, other DLPack producers) and out=None take the general
# path (_EngineBase._prepare). Measured per call on the host (iiwa, B = 1, torch CPU
# tensors): to_dlpack 0.19 us a tensor, against 0.3 us for data_ptr(), stride(),
# shape, dtype and device read one by one, so tensors go over as capsules.
_DIRECT_IN = {type(None): _as_is, np.ndarray: _as_is}
_DIRECT_OUT = {np.ndarray: _numpy_out}


_DTYPE_NAMES = {}  # dtype object -> its name, filled as dtypes are seen


def _dtype_name(x):
    """'float32', 'float64', or another dtype's name, of an array-like's dtype."""
    d = getattr(x, "dtype", None)
    if d is None:
        return None
    try:
        return _DTYPE_NAMES[d]
    except (KeyError, TypeError):  # not seen yet, or not hashable
        pass
    if _is_torch(x):
        name = str(d).replace("torch.", "")
    else:
        try:
            name = np.dtype(d).name
        except TypeError:
            name = str(d)
    try:
        _DTYPE_NAMES[d] = name
    except TypeError:
        pass
    return name


def _normalize_dtype(dtype):
    try:
        name = np.dtype(dtype).name
    except TypeError:
        name = str(dtype).replace("torch.", "")
    if name not in _FLOAT_NAMES:
        raise DTypeError(f"dtype must be float32 or float64, got {dtype!r}")
    return name


_NOT_ARRAYS = (list, tuple, int, float)


def _inputs(named, dtype=None):
    """The call's arrays, as given (no copy); Python lists, tuples and scalars (not
    arrays) become NumPy arrays of the call's dtype. Returns (arrays, dtype name of the
    first array)."""
    first = dtype
    out = []
    convert = False
    for _, x in named:
        if isinstance(x, _NOT_ARRAYS):
            convert = True
        elif first is None and x is not None:
            first = _dtype_name(x)
        out.append(x)
    first = first or "float64"
    if convert:
        to = first if first in _FLOAT_NAMES else "float64"
        out = [np.asarray(x, dtype=to) if isinstance(x, _NOT_ARRAYS) else x for x in out]
    return out, first


def _lead_of(q, name="q"):
    shape = tuple(getattr(q, "shape", ()))
    if len(shape) not in (1, 2):
        raise ShapeError(f"{name} has shape {shape}, expected (nq,) or (B, nq)")
    return shape[:-1]


def _entry_major_mass(q, nv, dtype):
    """The default result of a mass matrix on CUDA arrays (see _entry_major)."""
    return _entry_major(q, nv, nv, dtype)


def _entry_major(q, rows, cols, dtype):
    """The default (B, rows, cols) result of a per-instance matrix on CUDA arrays (the
    mass matrix, the derivatives): a view of entry-major memory (M[b, i, j] at
    (i * cols + j) * B + b), the layout the kernels store coalesced, so a call costs
    what the C++ engine's device row costs.
    Indexing, matmul, torch.linalg and CuPy read it as any strided array;
    .contiguous() / cupy.ascontiguousarray copy it row-major, and an out= array
    of any layout (row-major included) is written as given. None (a row-major
    result from _empty) for one state, JAX arrays (no strides) and host arrays."""
    if getattr(q, "ndim", 0) != 2:
        return None
    b = q.shape[0]
    if type(q).__module__.startswith("torch"):
        if not q.is_cuda:
            return None
        # one allocation with the view's strides, on q's device, in the engine's dtype
        dtypes = _Torch.dtypes or _Torch.load().dtypes
        return q.new_empty_strided((b, rows, cols), (1, cols * b, b), dtype=dtypes[dtype])
    if type(q).__module__.startswith("cupy"):
        import cupy

        with q.device:
            return cupy.empty((rows, cols, b), dtype=dtype).transpose(2, 0, 1)
    return None


def _empty(where, shape, dtype):
    """A new result array of the inputs' kind on their device: NumPy for host arrays
    (a torch CPU tensor for torch inputs), a torch / CuPy / JAX array on the inputs'
    CUDA device. JAX arrays are immutable: a new one is made (jnp.empty) and written
    through DLPack before anyone else sees it."""
    kind, like = where.kind, where.like
    if kind == "torch":
        dtypes = _Torch.dtypes or _Torch.load().dtypes
        if where.cuda is not None:
            # like.new_empty_strided: the cheapest of torch's allocating calls
            # (bench/python/torch_alloc_cost.py, bench/results/raw/python-call-profile-h200.txt:
            # 4.6 us against 7.1 for torch.empty on the same host)
            strides, n = [], 1
            for d in reversed(shape):
                strides.append(n)
                n *= d
            return like.new_empty_strided(shape, tuple(reversed(strides)), dtype=dtypes[dtype])
        import torch

        return torch.empty(shape, dtype=dtypes[dtype], device=like.device)
    if where.cuda is None:
        if kind == "jax":
            import jax.numpy as jnp

            return jnp.empty(shape, dtype, device=next(iter(like.devices())))
        return np.empty(shape, dtype=dtype)
    if kind == "cupy":
        import cupy

        with cupy.cuda.Device(where.cuda):
            return cupy.empty(shape, dtype=dtype)
    if kind == "jax":
        import jax.numpy as jnp

        return jnp.empty(shape, dtype, device=next(iter(like.devices())))
    raise DeviceError(
        f"cannot allocate a result for a CUDA array of type {type(like).__name__}: pass out= "
        "(a torch or CuPy array on the same device)"
    )


def _writable(out, where):
    """out as the extension writes it: JAX arrays (results this module made) through
    DLPack, CUDA arrays as capsules (no synchronisation), host arrays as they are."""
    if where.kind == "jax" and _kind(out) == "jax":
        return out.__dlpack__(stream=where.stream) if where.cuda is not None else out.__dlpack__()
    return _handover(out, "out", where)


def _check_out(out):
    if isinstance(out, (list, tuple)) or getattr(out, "shape", None) is None:
        raise DTypeError(f"out must be an array (NumPy or DLPack), got {type(out).__name__}")
    if _kind(out) == "jax":
        raise ShapeError("out is a JAX array: JAX arrays are immutable; leave out=None (a new JAX array is returned)")
    if isinstance(out, np.ndarray) and not out.flags.writeable:
        raise ShapeError("out is read-only")


def _finish(where):
    """JAX knows nothing of the stream scandyn's work was queued on: a JAX result is
    handed back only once that work is done (the one synchronisation of the device
    path, JAX only)."""
    if where.kind == "jax" and where.cuda is not None:
        _ext.synchronize_stream(where.stream)


def _host_int32(x):
    """A device array of failed DoFs (torch, CuPy, JAX) read back as a C-contiguous
    NumPy int32 array (the caller has waited for the stream)."""
    kind = _kind(x)
    if kind == "torch":
        x = x.cpu().numpy()
    elif kind == "cupy":
        x = x.get()
    return np.ascontiguousarray(np.asarray(x), dtype=np.int32)


def _call(fn, *args, **kw):
    try:
        return fn(*args, **kw)
    except TypeError as e:
        _reraise(e)


def _reraise(e):
    """Raises a TypeError of the extension's argument parsing as the DTypeError that
    says which arrays it reads; any other TypeError as it is."""
    if "incompatible function arguments" not in str(e):
        raise e
    raise DTypeError(
        "cannot read the arrays of this call without a copy: each must be a float32 or "
        "float64 array in host memory or CUDA device memory (buffer protocol or DLPack) whose "
        "strides are multiples of its item size, and out must be writable"
    ) from e


# ---- engines ------------------------------------------------------------------------


_HOST_AUTO = []  # backend="auto" on host arrays: "openmp", or "serial" where OpenMP is unusable (found once)


def _resolve_backend(backend):
    if backend == "auto":
        if not _HOST_AUTO:
            _HOST_AUTO.append("openmp" if not _ext.backend_unusable("openmp") else "serial")
        return _HOST_AUTO[0]
    return backend


def _devices_text(devices):
    """devices= as BackendOptions::devices' text (parse_devices in scandyn/sharded.hpp):
    None for the current device only (None, "current", an empty list), else "all" or
    the ordinals joined by commas ("0,1"; the library names a bad entry). TypeError for
    anything that is not a string or a list of ints."""
    if devices is None:
        return None
    if isinstance(devices, str):
        return None if devices in ("", "current") else devices
    if isinstance(devices, (bool, int, np.integer)):
        raise TypeError(f"devices must be 'all', 'current', a list of CUDA ordinals or None, got "
                        f"{devices!r} (one device: devices=[{devices!r}] or device={devices!r})")
    try:
        items = list(devices)
    except TypeError:
        raise TypeError(f"devices must be 'all', 'current', a list of CUDA ordinals or None, got "
                        f"{type(devices).__name__}") from None
    for d in items:
        if isinstance(d, bool) or not isinstance(d, (int, np.integer)):
            raise TypeError(f"devices must list CUDA ordinals (ints), got {d!r} in {devices!r}")
    return ",".join(str(int(d)) for d in items) if items else None


def _backend_for_devices(backend, devices_text, device):
    """The backend of an engine made with devices=: "auto" becomes "cuda" (only the cuda
    backend runs on devices; any other backend is refused by the library, naming the
    devices). DeviceError for device= and devices= together."""
    if devices_text is None:
        return backend
    if device is not None:
        raise DeviceError(f"device={device!r} and devices={devices_text!r} together: device= makes an engine "
                          "on one CUDA device (for host and CUDA arrays), devices= shards host batches across "
                          "devices; pass one of them")
    return "cuda" if backend == "auto" else backend


class _EngineBase:
    """One engine of the library (scandyn/engine.hpp). On host arrays a call runs the
    engine's compute() and returns when done; on CUDA arrays (backend='cuda', the arrays
    on the engine's device) it queues compute_async() on the caller's stream (``stream=``,
    else torch's or CuPy's current stream) and returns at once: no copy, no
    synchronisation.

    ``devices`` (backend 'cuda'; 'auto' becomes 'cuda'): the CUDA devices a host batch
    is sharded across ('all', a list of ordinals such as [0, 1], a device named twice
    running two shards there; None or 'current': the current device only). Each device
    gets its own engine for a contiguous share of the instances (max_batch is the whole
    batch's), the shards run at once and write the results in place, in the caller's
    layout; an error from a shard begins "device D: ". CUDA arrays run on their own
    device only: an engine sharded over several devices refuses them (DeviceError)."""

    _ext_class = None

    def __init__(self, model, backend, max_batch, dtype, device=None, devices=None, **options):
        if not isinstance(model, Model):
            raise TypeError(f"model must be a scandyn.Model (scandyn.load_model), got {type(model).__name__}")
        self.model = model
        self._dtype = _normalize_dtype(dtype)
        max_batch = int(max_batch)
        if not 1 <= max_batch <= _MAX_INDEX:
            raise ShapeError(f"max_batch must be from 1 to {_MAX_INDEX} (the engines' instance index), got {max_batch}")
        text = _devices_text(devices)
        backend = _backend_for_devices(backend, text, device)
        if device is not None:
            options["device"] = int(device)
        if text is not None:
            options["devices"] = text
        self._e = self._ext_class(model._m, self._dtype, _resolve_backend(backend), max_batch, **options)
        self._nv = self._e.nv  # the call path's copies (the properties ask the extension)
        self._cuda = self._e.backend == "cuda"

    backend = property(lambda self: self._e.backend, doc="'serial', 'openmp' or 'cuda'")
    strategy = property(lambda self: self._e.strategy, doc="the variant the engine runs")
    exact = property(lambda self: self._e.exact, doc="bit-identical to the serial reference")
    max_batch = property(lambda self: self._e.max_batch)
    nv = property(lambda self: self._e.nv)
    device = property(lambda self: self._e.device,
                      doc="the CUDA device of a cuda engine (of all its shards), -1 otherwise or for an engine "
                          "sharded over several devices")
    devices = property(lambda self: list(self._e.devices),
                       doc="the CUDA device of each shard (devices=), [device] for a cuda engine, [] on the CPU")
    dtype = property(lambda self: np.dtype(self._dtype))

    _names = ()  # the names of __call__'s arrays, for the messages

    def _prepare(self, arrays, out, stream, tail=()):
        """(where, the arrays as the extension takes them, out as given or made, out as
        written), for the arrays named self._names. The common calls (q a torch tensor or
        a NumPy array, every array and out of a type in _DIRECT_IN / _DIRECT_OUT) take a
        short path: one dictionary look-up and the hand-over per array, the first array's
        device, the stream, a result like q when out is None."""
        q = arrays[0]
        try:
            handed = [_DIRECT_IN[type(x)](x) for x in arrays]
            out_hand = _DIRECT_OUT[type(out)] if out is not None else None
        except KeyError:
            return self._prepare_general(arrays, out, stream, tail)
        if type(q) is np.ndarray:
            where = _Where(None, "numpy", None, q)
            if stream is not None:
                _stream_handle(stream)  # checked, unused on the host
        elif q is None:
            return self._prepare_general(arrays, out, stream, tail)
        else:  # a torch tensor
            cuda = q.get_device() if q.is_cuda else None
            s = None
            if cuda is not None:
                if stream is not None:
                    s = _stream_handle(stream)
                else:  # torch's current stream of the device (the cheapest of torch's APIs)
                    s = (_Torch.raw_stream or _Torch.load().raw_stream)(cuda)
            elif stream is not None:
                _stream_handle(stream)
            where = _Where(cuda, "torch", s, q)
        if out is None:
            out = _empty(where, _lead_of(q) + (self._nv,) + tail, self._dtype)
            out_hand = _DIRECT_OUT.get(type(out))
            if out_hand is None:  # a type not seen yet (torch.Tensor after only Parameters)
                return where, handed, out, _writable(out, where)
        return where, handed, out, out_hand(out)

    def _prepare_general(self, arrays, out, stream, tail):
        names = self._names
        arrays, _ = _inputs(zip(names, arrays), self._dtype)
        where = _where(arrays[0], stream)
        if out is None:
            out = _empty(where, _lead_of(arrays[0]) + (self.nv,) + tail, self._dtype)
        else:
            _check_out(out)
        if where.cuda is None and where.kind == "numpy":
            handed = arrays  # NumPy on the host: read as they are (the buffer protocol)
        else:
            handed = [_handover(a, n, where) for a, n in zip(arrays, names)]
        return where, handed, out, _writable(out, where)

    def __repr__(self):
        devs = self.devices
        dev = ((f", devices={devs}" if len(devs) > 1 else f", device={self.device}")
               if self.backend == "cuda" else "")
        return (
            f"scandyn.{type(self).__name__}(model={self.model.name!r}, backend={self.backend!r}, "
            f"strategy={self.strategy!r}, dtype={self._dtype}, max_batch={self.max_batch}{dev})"
        )


class InverseDynamics(_EngineBase):
    """tau = ID(q, qd, qdd, fext): RNEA with gravity, for up to max_batch instances.
    ``strategy``: 'auto', 'recursion', 'scan-local', 'scan-world' (CPU). ``device``: the
    CUDA device of a cuda engine (default: the current one); ``devices``: the devices a
    host batch is sharded across (see _EngineBase)."""

    _ext_class = _ext.InverseDynamics
    _names = ("q", "qd", "qdd", "fext")

    def __init__(self, model, backend="auto", max_batch=1, dtype=np.float64, strategy="auto", threads=0,
                 device=None, devices=None):
        super().__init__(model, backend, max_batch, dtype, device, devices, strategy=strategy, threads=threads)

    def __call__(self, q, qd, qdd, fext=None, out=None, stream=None):
        where, (q, qd, qdd, fext), out, w = self._prepare((q, qd, qdd, fext), out, stream)
        try:
            self._e.compute(q, qd, qdd, w, fext, where.stream or 0)
        except TypeError as e:
            _reraise(e)
        if where.kind == "jax":
            _finish(where)
        return out


class BiasForces(_EngineBase):
    """h = RNEA(q, qd, 0, fext): Coriolis, centrifugal and gravity forces."""

    _ext_class = _ext.BiasForces
    _names = ("q", "qd", "fext")

    def __init__(self, model, backend="auto", max_batch=1, dtype=np.float64, strategy="auto", threads=0,
                 device=None, devices=None):
        super().__init__(model, backend, max_batch, dtype, device, devices, strategy=strategy, threads=threads)

    def __call__(self, q, qd, fext=None, out=None, stream=None):
        where, (q, qd, fext), out, w = self._prepare((q, qd, fext), out, stream)
        try:
            self._e.compute(q, qd, w, fext, where.stream or 0)
        except TypeError as e:
            _reraise(e)
        if where.kind == "jax":
            _finish(where)
        return out


class MassMatrix(_EngineBase):
    """M(q) by the CRBA: (B, nv, nv) (or (nv, nv) for one state), both triangles written."""

    _ext_class = _ext.MassMatrix
    _names = ("q",)

    def __init__(self, model, backend="auto", max_batch=1, dtype=np.float64, threads=0, device=None, devices=None):
        super().__init__(model, backend, max_batch, dtype, device, devices, threads=threads)

    def __call__(self, q, out=None, stream=None):
        if out is None and self._cuda:
            out = _entry_major_mass(q, self._nv, self._dtype)
        where, (q,), out, w = self._prepare((q,), out, stream, (self._nv,))
        try:
            self._e.compute(q, w, where.stream or 0)
        except TypeError as e:
            _reraise(e)
        if where.kind == "jax":
            _finish(where)
        return out


class ForwardDynamics(_EngineBase):
    """qdd = FD(q, qd, tau, fext). ``method``: 'auto', 'aba', 'jsi', 'parallel' (chains),
    'hybrid' (cuda, host arrays only). An instance whose pivot is not positive and finite
    raises ForwardDynamicsError (its ``status`` says which; those instances' entries of
    out are left unwritten); ``last_status`` is the last call's scandyn.Status.
    ``fd_check``: 'auto', 'on', 'off': the run-time check of each result (docs/accuracy.md);
    an instance above ``fd_check_tol`` (0: 1e-4 float, 1e-10 double) raises
    ForwardDynamicsError too, unless ``fallback_aba`` (jsi) or ``fallback_double``
    (float32) computes it again within the threshold (``status.retried`` counts them).

    On CUDA arrays a call only queues the work: the failed DoFs go to a (B,) int32 array
    on the device, ``failed_dof`` (the engine's own, or the caller's ``failed_dof=``), and
    nothing is raised until ``check()`` (or ``check=True``) waits for the stream and reads
    them. JAX calls wait anyway (see docs/python.md) and check at once."""

    _ext_class = _ext.ForwardDynamics
    _names = ("q", "qd", "tau", "fext")

    def __init__(self, model, backend="auto", max_batch=1, dtype=np.float64, method="auto",
                 fallback_aba=False, threads=0, fd_check="auto", fd_check_tol=0.0, fallback_double=False,
                 device=None, devices=None):
        super().__init__(model, backend, max_batch, dtype, device, devices, method=method, fallback_aba=fallback_aba,
                         threads=threads, fd_check=fd_check, fd_check_tol=float(fd_check_tol),
                         fallback_double=fallback_double)
        self.last_status = None
        self.failed_dof = None  # CUDA calls: the last call's (B,) int32 device array
        self._pending = None  # (failed_dof, stream) of a CUDA call not checked yet
        self._failed_buffers = {}  # (kind, device) -> (max_batch,) int32 device array; (kind, device, B) -> its [:B]

    method = property(lambda self: self._e.method, doc="the method run ('auto' resolved)")

    def _failed_buffer(self, where, batch):
        view = self._failed_buffers.get((where.kind, where.cuda, batch))  # the view of the last calls
        if view is not None:
            return view
        key = (where.kind, where.cuda)
        buf = self._failed_buffers.get(key)
        if buf is None:
            n = self.max_batch
            if where.kind == "torch":
                import torch

                buf = torch.empty(n, dtype=torch.int32, device=where.like.device)
            elif where.kind == "cupy":
                import cupy

                with cupy.cuda.Device(where.cuda):
                    buf = cupy.empty(n, dtype=np.int32)
            elif where.kind == "jax":  # a fresh one per call, written through DLPack, read at once
                import jax.numpy as jnp

                return jnp.empty(batch, np.int32, device=next(iter(where.like.devices())))
            else:
                raise DeviceError(f"pass failed_dof= (a (B,) int32 array on CUDA device {where.cuda}) "
                                  f"for arrays of type {type(where.like).__name__}")
        view = buf[:batch]
        # the buffers, and the view of this batch size only
        kept = {k: v for k, v in self._failed_buffers.items() if len(k) == 2}
        kept[key] = buf
        kept[(where.kind, where.cuda, batch)] = view
        self._failed_buffers = kept
        return view

    _what = "forward dynamics"  # the computation, as the errors name it

    def _failed_of(self, where, failed_dof):
        """CUDA calls: the (B,) int32 failed-DoF array (the caller's failed_dof, else the
        engine's own) and its handover to the extension; (None, None) on the host."""
        if where.cuda is None:
            return None, None
        failed = failed_dof
        if failed is None:
            lead = where.like.shape[:-1]  # (B,) or () (the extension checks q's shape)
            failed = self._failed_buffer(where, lead[0] if len(lead) == 1 else 1)
        hand = _DIRECT_OUT.get(type(failed))
        return failed, (hand(failed) if hand is not None else _writable(failed, where))

    def _settle(self, status, where, failed, check):
        """After a call: a queued CUDA call keeps its failed DoFs for check() (run at once
        with check=True, and for JAX); a host call's failure raises ForwardDynamicsError."""
        if status.queued:
            self.failed_dof = failed
            self._pending = (failed, where.stream)
            self.last_status = None
            if check or where.kind == "jax":
                _finish(where)
                self.check()
            return
        self.last_status = status
        if not status.ok:
            raise ForwardDynamicsError(f"{self._what} failed: {status.message}", status)

    def __call__(self, q, qd, tau, fext=None, out=None, stream=None, failed_dof=None, check=False):
        where, (q, qd, tau, fext), out, w = self._prepare((q, qd, tau, fext), out, stream)
        failed, fd = self._failed_of(where, failed_dof)
        try:
            status = self._e.compute(q, qd, tau, w, fext, fd, where.stream or 0)
        except TypeError as e:
            _reraise(e)
        self._settle(status, where, failed, check)
        return out

    def check(self):
        """Waits for the stream of the last CUDA call, reads its failed DoFs and raises
        ForwardDynamicsError as a host call would (the failed instances' entries of out
        were left unwritten). Returns the call's scandyn.Status. A no-op after host calls
        (they raise at once)."""
        if self._pending is None:
            return self.last_status
        failed, stream = self._pending
        self._pending = None
        _ext.synchronize_stream(stream)
        status = _ext.status_of_failed_dofs(_host_int32(failed), self.method)
        self.last_status = status
        if not status.ok:
            raise ForwardDynamicsError(f"{self._what} failed: {status.message}", status)
        return status


# ---- the function API: engines cached per model ------------------------------------


def _cached(cls, key_option, model, backend, first, devices=None, **options):
    if not isinstance(model, Model):
        raise TypeError(f"model must be a scandyn.Model (scandyn.load_model), got {type(model).__name__}")
    dtype = _dtype_name(first)
    if dtype not in _FLOAT_NAMES:
        raise DTypeError(f"q has dtype {dtype}, expected float32 or float64")
    lead = _lead_of(first)
    batch = lead[0] if lead else 1
    device = _cuda_device(first, _kind(first), "q")
    text = _devices_text(devices)
    if text is not None and device is not None:
        # CUDA arrays run on their own device: devices= may only name that one
        if _ext.parse_devices(text) != [device]:
            raise DeviceError(f"devices={devices!r} with arrays on CUDA device {device}: CUDA arrays run on "
                              "their own device, not sharded (devices= shards host arrays: NumPy, CPU torch "
                              "tensors); leave devices= out for CUDA arrays")
        text = None
    if text is not None:
        backend = _backend_for_devices(backend, text, None)
    if device is not None and backend == "auto":
        backend = "cuda"  # "auto" follows the arrays
    backend = _resolve_backend(backend)
    if backend != "cuda":
        device = None
    if text is not None:
        options["devices"] = text
    key = (cls.__name__, backend, dtype, key_option, device, text)
    engine = model._engines.get(key)
    if engine is None or engine.max_batch < batch:
        engine = None  # the old engine's device memory goes before the new one is made
        model._engines.pop(key, None)
        if device is not None:
            options["device"] = device
        engine = cls(model, backend=backend, max_batch=max(batch, 1), dtype=dtype, **options)
        model._engines[key] = engine
    return engine


def inverse_dynamics(model, q, qd, qdd, fext=None, backend="auto", out=None, stream=None, devices=None):
    """tau = ID(q, qd, qdd, fext), gravity included. q, qd, qdd: (B, nv) or (nv,);
    fext: optional (B, nv, 6) body wrenches [moment; force] in body frames. Returns tau
    (out when given). CUDA arrays: queued on ``stream`` (default: the array library's
    current stream), no synchronisation. ``devices`` ('all', [0, 1], ...): host arrays
    sharded across those CUDA devices (backend 'auto' becomes 'cuda'); with CUDA arrays
    only their own device may be named."""
    (q, qd, qdd, fext), _ = _inputs([("q", q), ("qd", qd), ("qdd", qdd), ("fext", fext)])
    return _cached(InverseDynamics, None, model, backend, q, devices)(q, qd, qdd, fext=fext, out=out, stream=stream)


def bias_forces(model, q, qd, fext=None, backend="auto", out=None, stream=None, devices=None):
    """h = RNEA(q, qd, 0, fext): (B, nv) or (nv,). ``devices``: as inverse_dynamics."""
    (q, qd, fext), _ = _inputs([("q", q), ("qd", qd), ("fext", fext)])
    return _cached(BiasForces, None, model, backend, q, devices)(q, qd, fext=fext, out=out, stream=stream)


def mass_matrix(model, q, backend="auto", out=None, stream=None, devices=None):
    """M(q): (B, nv, nv), or (nv, nv) for q of shape (nv,). ``devices``: as inverse_dynamics."""
    (q,), _ = _inputs([("q", q)])
    return _cached(MassMatrix, None, model, backend, q, devices)(q, out=out, stream=stream)


def forward_dynamics(model, q, qd, tau, fext=None, method="auto", backend="auto", out=None, stream=None,
                     check=None, devices=None):
    """qdd = FD(q, qd, tau, fext), gravity included: (B, nv) or (nv,). Raises
    ForwardDynamicsError (with .status) when an instance's pivot is not positive. On CUDA
    arrays that check waits for the stream (check=None: yes, as on the host); check=False
    only queues the work (failures are then not reported: use a ForwardDynamics engine
    and its check() to read them later). ``devices``: as inverse_dynamics."""
    (q, qd, tau, fext), _ = _inputs([("q", q), ("qd", qd), ("tau", tau), ("fext", fext)])
    engine = _cached(ForwardDynamics, method, model, backend, q, devices, method=method)
    return engine(q, qd, tau, fext=fext, out=out, stream=stream, check=check is None or bool(check))
