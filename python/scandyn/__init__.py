"""scandyn: rigid-body dynamics of kinematic trees (C++17/CUDA), from Python.

    import numpy as np, scandyn as sd
    m = sd.load_model("iiwa")                      # or "rope:1000", a URDF path
    q = np.zeros((1024, m.nv)); qd = np.zeros_like(q); qdd = np.zeros_like(q)
    tau = sd.inverse_dynamics(m, q, qd, qdd)       # (1024, nv), float64 like q
    M = sd.mass_matrix(m, q)                       # (1024, nv, nv)
    T = sd.frame_placements(m, q, ["iiwa_link_7"])  # (1024, 1, 4, 4) world poses
    J = sd.frame_jacobians(m, q, ["iiwa_link_7"])   # (1024, 1, 6, nv), rows [angular; linear]

Arrays are batch-first, (B, nv) or (nv,); precision follows their dtype (float32 or
float64); they reach the library's engines with their own strides, without a copy.
docs/python.md has the whole API, the zero-copy rules and the errors.
"""

import os as _os
import sys as _sys


def _load_extension():
    """Imports the extension module with RTLD_DEEPBIND (Linux): the module and the
    libraries it brings (urdfdom, tinyxml, console_bridge) resolve their symbols in
    their own dependencies first, so a library that another package loaded into the
    global scope with copies of C++ runtime functions (torch's RTLD_GLOBAL CUDA
    dependencies, e.g. libcufile, export std::istringstream constructors of a statically
    linked libstdc++) cannot interpose on the URDF parser. Not with LD_PRELOAD (an
    allocator such as jemalloc, or a sanitizer's runtime, must stay visible to every
    library: deep binding would hide it from these). SCANDYN_NO_DEEPBIND=1 imports it
    with the interpreter's flags too (docs/python.md)."""
    deep = getattr(_os, "RTLD_DEEPBIND", 0)
    flags = _sys.getdlopenflags()
    if deep and not _os.environ.get("SCANDYN_NO_DEEPBIND") and not _os.environ.get("LD_PRELOAD"):
        _sys.setdlopenflags(flags | deep)
    try:
        from . import _scandyn as ext
    finally:
        _sys.setdlopenflags(flags)
    return ext


_scandyn = _load_extension()
from . import models  # noqa: E402
from ._api import (  # noqa: E402
    BiasForces,
    ForwardDynamics,
    InverseDynamics,
    MassMatrix,
    Model,
    Status,
    bias_forces,
    forward_dynamics,
    inverse_dynamics,
    load_model,
    mass_matrix,
)
from .simulator import Simulator  # noqa: E402
from .kinematics import Kinematics, frame_jacobians, frame_placements  # noqa: E402
from .hybrid import HybridDynamics, hybrid_dynamics  # noqa: E402
from .loops import (ConstrainedForwardDynamics, Loops, constrained_forward_dynamics, generator_loops,  # noqa: E402
                    load_loops, loop_residual, parse_loops)
from .errors import (  # noqa: E402
    BackendError,
    DeviceError,
    DTypeError,
    Error,
    ForwardDynamicsError,
    LoopError,
    ModelError,
    SceneError,
    ShapeError,
    SimulationError,
)

__version__ = _scandyn.__version__
has_cuda = _scandyn.has_cuda  # the CUDA backend is compiled in (a GPU may still be missing)
has_openmp = _scandyn.has_openmp
# the simulator's sparse loop solver (scene "loop_solver": "sparse"; docs/loops.md): the
# factor graph's CHOLMOD solver, in a CMake build with SuiteSparse (not in a wheel)
has_sparse_loops = _scandyn.has_sparse_loops


def backend_unusable(backend):
    """Why a backend ("serial", "openmp", "cuda") cannot run here ("not available in this
    build", "no usable CUDA device: ..."), or "" when it can."""
    return _scandyn.backend_unusable(backend)


def __getattr__(name):
    # scandyn.envs (Gymnasium environments) is imported on first use: it needs gymnasium
    if name == "envs":
        import importlib

        return importlib.import_module(".envs", __name__)
    raise AttributeError(f"module 'scandyn' has no attribute {name!r}")


__all__ = [
    "BackendError", "BiasForces", "DTypeError", "DeviceError", "Error", "ForwardDynamics",
    "ForwardDynamicsError", "InverseDynamics", "Kinematics", "MassMatrix", "Model", "ModelError", "ShapeError",
    "Status", "backend_unusable", "bias_forces", "forward_dynamics", "frame_jacobians", "frame_placements", "has_cuda", "has_openmp", "has_sparse_loops", "inverse_dynamics",
    "load_model", "mass_matrix", "models",
    "SceneError", "SimulationError", "Simulator",
    "HybridDynamics", "hybrid_dynamics",
    "ConstrainedForwardDynamics", "LoopError", "Loops", "constrained_forward_dynamics", "generator_loops",
    "load_loops", "loop_residual", "parse_loops",
]
