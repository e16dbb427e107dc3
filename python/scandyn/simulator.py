"""scandyn.Simulator: B instances of a scene stepped by the library's simulator
(scandyn/sim/simulator.hpp), with the state as zero-copy views.

    sim = sd.Simulator("scenes/iiwa_rl.json")           # or a dict with the same keys
    sim.step(tau)                                       # tau (B, nv), or None: zero torques
    sim.q, sim.qd                                       # (B, nq), (B, nv) views of the simulator's state
    sim.reset([3, 17])                                  # those instances restart
    sim.contact_forces()                                # (B, P, 3) views of the last step's contacts

The binding is python/src/simulator.cpp; docs/python.md ("The simulator") has the rules.
"""

import json
import os

import numpy as np

from . import _scandyn as _ext
from ._api import resolve_model_spec
from .errors import DeviceError, ShapeError


def _torch():
    try:
        import torch
    except ImportError:  # pragma: no cover - only without torch
        return None
    return torch


def _is_torch(x):
    return type(x).__module__.startswith("torch")


def _device_ordinal(device):
    """The CUDA ordinal of a device= argument: -1 for None, "cuda" and "cpu" (the current
    device; a CPU scene ignores it), N for N, "cuda:N" and torch.device("cuda", N)."""
    if device is None:
        return -1
    if isinstance(device, bool):
        raise TypeError(f"device must be None, an ordinal, 'cuda:N' or a torch.device, got {device!r}")
    if isinstance(device, (int, np.integer)):
        if device < 0:
            raise DeviceError(f"device must be a CUDA ordinal >= 0, got {device}")
        return int(device)
    index = getattr(device, "index", None) if not isinstance(device, str) else None
    if index is not None:  # a torch.device with an index
        return int(index)
    text = str(device)
    if text in ("cuda", "cpu"):
        return -1
    if text.startswith("cuda:") and text[5:].isdigit():
        return int(text[5:])
    raise DeviceError(f"device must be None, an ordinal, 'cuda', 'cuda:N' or a torch.device, got {device!r}")


class Simulator:
    """B instances of one scene (docs/scenes.md), stepped by the library's simulator.

    ``scene``: a scene file's path, or a dict with the keys of a scene file (serialised to
    JSON and read by the library's scene reader: the same keys, checks and messages; the
    model is looked up as :func:`scandyn.load_model` does, so ``"iiwa"`` finds the shipped
    arm). ``backend``: None (the scene's "backend"), "serial", "openmp", "cuda" or "auto"
    (cuda where it is built and a GPU is usable, else openmp; ``backend_note`` says why). The precision is the scene's ("float" or
    "double", default double). Errors: SceneError (a bad key, with the library's one-line
    message), BackendError (a backend that is not built or cannot run the scene).

    State: :attr:`q` and :attr:`qd` are the simulator's own buffers, no copies: (B, nq) and
    (B, nv) views of the (nq x B), (nv x B) structures of arrays the simulator keeps (nq > nv
    for a floating base and ball joints; entry (DoF i, instance
    b) at element i * B + b, so the view's strides are (1, B) elements). NumPy arrays on
    the CPU backends; on cuda, torch tensors on the simulator's GPU (the raw DLPack object
    without torch). Writes through them change the simulation. A view keeps the simulator
    alive; it stays valid for the simulator's whole life (the buffers never move).
    ``arrays``: "auto" (as above), "numpy", "torch" (also on the CPU) or "dlpack" (a
    nanobind array that torch / CuPy / JAX ``from_dlpack`` take): the kind of the views.
    ``device`` (cuda): the GPU the simulator lives on: None (the current CUDA device:
    torch.cuda.set_device's, e.g. LOCAL_RANK's under torchrun), an ordinal, "cuda:N" or a
    torch.device; its steps run there whatever device is current when they are called.
    """

    def __init__(self, scene, backend=None, arrays="auto", device=None):
        ordinal = _device_ordinal(device)
        if isinstance(scene, dict):
            scene = dict(scene)
            if isinstance(scene.get("model"), str):
                scene["model"] = resolve_model_spec(scene["model"])
            try:
                text = json.dumps(scene, allow_nan=False)
            except (TypeError, ValueError) as e:
                from .errors import SceneError

                raise SceneError(f"<dict>: cannot be written as JSON: {e}") from None
            self._s = _ext.Simulator("", text, "<dict>", os.getcwd(), backend, ordinal)
        else:
            self._s = _ext.Simulator(os.fspath(scene), None, "", "", backend, ordinal)
        if arrays == "auto":
            arrays = "numpy" if not self._s.on_device else ("torch" if _torch() is not None else "dlpack")
        if arrays not in ("numpy", "torch", "dlpack"):
            raise ValueError(f"arrays must be 'auto', 'numpy', 'torch' or 'dlpack', got {arrays!r}")
        self._arrays = arrays
        self._q = self._s.view(False, arrays)
        self._qd = self._s.view(True, arrays)
        self._contact_views = {}  # field -> the view of the contact readings, made on first use

    # ---- state and properties ----------------------------------------------------------

    @property
    def q(self):
        """(B, nq) joint positions (nq = nv unless the model has quaternions: a floating base's
        [p, quaternion x y z w] first, ball joints' quaternions): a view of the simulator's state (with arrays="dlpack" a new
        object on each access: a DLPack export can be consumed once)."""
        return self._q if self._arrays != "dlpack" else self._s.view(False, "dlpack")

    @property
    def qd(self):
        """(B, nv) joint velocities: a view of the simulator's state (see q)."""
        return self._qd if self._arrays != "dlpack" else self._s.view(True, "dlpack")
    nv = property(lambda self: self._s.nv, doc="degrees of freedom of the scene's model")
    nq = property(lambda self: self._s.nq, doc="entries of q (nv + 1 with a floating base, + 1 per ball joint)")
    num_instances = property(lambda self: self._s.num_instances, doc="B, the scene's instances")
    dt = property(lambda self: self._s.dt, doc="the time step (s)")
    t = property(lambda self: self._s.t, doc="simulated time: steps taken since construction times dt")
    steps = property(lambda self: self._s.steps, doc="steps taken since construction")
    backend = property(lambda self: self._s.backend, doc="'serial', 'openmp' or 'cuda'")
    precision = property(lambda self: "float" if self._s.dtype == "float32" else "double")
    dtype = property(lambda self: np.dtype(self._s.dtype), doc="float32 or float64: the state's and tau's dtype")
    strategy = property(lambda self: self._s.strategy,
                        doc="how a step runs: 'serial-aba', 'openmp-aba', 'openmp-engine-parallel', "
                            "'fused-aba', 'engine-parallel', 'engine-jsi_dense'")
    backend_note = property(lambda self: self._s.backend_note,
                            doc="for a scene whose backend was 'auto': why not cuda ('' when cuda was chosen)")

    @property
    def device(self):
        """'cpu', or 'cuda:N' for a scene on the GPU."""
        return f"cuda:{self._s.device}" if self._s.on_device else "cpu"

    # ---- stepping ----------------------------------------------------------------------

    def _stream(self, stream):
        """The caller's CUDA stream as an integer: the given one, else torch's current stream
        on the simulator's device (None on the CPU, or on cuda without torch: then the
        caller synchronises with :meth:`synchronize`)."""
        if not self._s.on_device:
            return None
        if stream is not None:
            return int(getattr(stream, "cuda_stream", getattr(stream, "ptr", stream)))
        torch = _torch()
        if torch is None:
            return None
        return int(torch.cuda.current_stream(self._s.device).cuda_stream)

    def _torques(self, tau):
        if tau is None:
            return None
        if isinstance(tau, (list, tuple)):
            tau = np.asarray(tau, dtype=self.dtype)
        if self._s.on_device and not (_is_torch(tau) or hasattr(tau, "__dlpack__")):
            raise DeviceError("tau must be a CUDA array on the simulator's device (a torch tensor, ...); "
                              "nothing is copied between devices")
        return tau

    def step(self, tau=None, check=True, stream=None):
        """Advances every instance by dt under the joint torques ``tau``: (B, nv) in the
        simulator's dtype and memory (NumPy / torch CPU on the CPU backends, a CUDA tensor on
        the simulator's GPU for cuda; any strides), or None for zero torques.

        ``check``: after the step, raise SimulationError when an instance failed (a forward
        dynamics pivot that is not positive: that instance kept its state; or a state that
        became non-finite: kept as computed), with the library's message; the status is then
        cleared. On cuda this reads the status back (a synchronisation); ``check=False``
        leaves the work queued (see :meth:`status`).

        CUDA work runs on the simulator's own stream, ordered after the work queued so far on
        ``stream`` (default: torch's current stream), and that stream waits for the step:
        torch code on that stream reads and writes :attr:`q` / :attr:`qd` in order with the
        steps, without a host synchronisation."""
        self._s.step(self._torques(tau), 1, check, self._stream(stream))

    def step_many(self, n, tau=None, check=True, stream=None):
        """``n`` steps with the same torques (held over the steps); one status check at the end."""
        self._s.step(self._torques(tau), int(n), check, self._stream(stream))

    def reset(self, indices=None, stream=None):
        """Puts instances back in the scene's initial state: all of them (None), or those
        listed (a sequence or integer array of instance indices, or a boolean mask of length B;
        NumPy or torch). A randomised initial state draws again from the scene's seeded
        generator (docs/scenes.md). IndexError for an index outside [0, B)."""
        if indices is not None:
            if _is_torch(indices):
                indices = indices.detach().cpu().numpy()
            idx = np.asarray(indices)
            if idx.dtype == bool:
                if idx.shape != (self.num_instances,):
                    raise ShapeError(f"a reset mask has shape {idx.shape}, expected ({self.num_instances},)")
                idx = np.flatnonzero(idx)
            elif idx.ndim != 1 and idx.size:
                raise ShapeError(f"reset indices have shape {idx.shape}, expected a flat list of instances")
            elif idx.size and not np.issubdtype(idx.dtype, np.integer):
                raise ShapeError(f"reset indices must be integers, got dtype {idx.dtype}")
            indices = [int(i) for i in idx.reshape(-1)]
        self._s.reset(indices, self._stream(stream))

    def status(self):
        """The steps' failures since the last clear: (failed instance-steps, first_instance,
        first_dof, message); message is '' when none failed. Synchronises on cuda."""
        return self._s.status()

    def clear_status(self):
        self._s.clear_status()

    def synchronize(self):
        """Waits for the simulator's queued work (cuda; nothing on the CPU backends)."""
        self._s.synchronize()

    # ---- contacts ----------------------------------------------------------------------

    num_contact_points = property(lambda self: self._s.num_contact_points,
                                  doc="P, the scene's contact points (effects.contacts; 0 without)")

    def _contact(self, field):
        if self._arrays == "dlpack":
            return self._s.contact_view(field, "dlpack")
        if field not in self._contact_views:
            self._contact_views[field] = self._s.contact_view(field, self._arrays)
        return self._contact_views[field]

    def contact_forces(self):
        """(B, P, 3) the total contact force on each contact point (world frame, N) in the
        last step (its first forward dynamics: the state the step started from); zeros
        before the first step. A zero-copy view of the simulator's readings
        (Simulator::contact_forces(); entry [b, k] is point k of effects.contacts, the listed
        points first, then all_links' in link order), in the state's dtype and memory, kept
        up to date by every step. ShapeError for a scene without effects.contacts."""
        return self._contact("force")

    def contact_depths(self):
        """(B, P) each point's largest penetration over the obstacles (m; 0 when apart), a
        view like :meth:`contact_forces`."""
        return self._contact("depth")

    def in_contact(self):
        """(B, P) int32: 1 where an obstacle pushed on the point in the last step, else 0; a
        view like :meth:`contact_forces`."""
        return self._contact("in_contact")

    def energy(self):
        """(B,) mechanical energy of every instance, float64 (a host copy of the state)."""
        return np.asarray(self._s.energy())

    def __repr__(self):
        return (f"scandyn.Simulator(num_instances={self.num_instances}, nv={self.nv}, dt={self.dt}, "
                f"backend={self.backend!r}, precision={self.precision!r}, strategy={self.strategy!r})")
