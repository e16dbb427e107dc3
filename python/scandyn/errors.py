"""scandyn's exceptions. Every error scandyn raises is a scandyn.Error; each class
also derives from the built-in exception a Python caller would expect, so
``except ValueError`` catches a bad shape and ``except TypeError`` a wrong dtype.
The messages are the library's own (the ones the command line prints)."""


class Error(Exception):
    """Base class of every scandyn exception."""


class ModelError(Error, ValueError):
    """A model that cannot be loaded: missing file, malformed URDF or generator spec,
    non-physical inertia (load_model(..., allow_nonphysical_inertia=True) waives the
    inertia checks), ..."""


class ShapeError(Error, ValueError):
    """An array of the wrong shape, leading shapes that differ between arguments, a batch
    beyond an engine's max_batch, an out= array whose entries overlap or that shares memory
    with an input, a strided array the engines cannot read without a copy."""


class DTypeError(Error, TypeError):
    """An array that is not float32 / float64, or arrays of one call with different dtypes."""


class DeviceError(Error, ValueError):
    """Arrays on a device scandyn cannot use from Python yet (CUDA arrays), or on different
    devices. scandyn never copies an array to another device behind the caller's back."""


class BackendError(Error, RuntimeError):
    """A backend that is not built or cannot run here, a model the chosen backend or method
    cannot take, an unknown backend / method / strategy name."""


class ForwardDynamicsError(Error, RuntimeError):
    """Forward dynamics failed for some instances (a pivot that is not positive and finite).
    ``status`` holds what failed (scandyn.Status: failed, first_instance, first_dof, reason,
    message, failed_dof); the failed instances' outputs were left unwritten."""

    def __init__(self, message, status=None):
        super().__init__(message)
        self.status = status


class SceneError(Error, ValueError):
    """A scene that cannot be read or is not valid (scandyn.Simulator): the library's one line
    naming the file (or "<dict>") and the key, e.g. "<dict>: effects.damping: expected a
    non-negative number or an array of 7 non-negative numbers, got -1"."""


class SimulationError(Error, RuntimeError):
    """A simulator step failed (Simulator.step with check=True): a forward dynamics whose pivot
    is not positive (those instances kept their state for that step) or a state that became
    non-finite (kept as computed). The message is the library's (sim::failure_message), e.g.
    "after step 2 (t = 0.002 s): the state became non-finite in 1 instance-step, first in instance 0:
    the state at DoF 0 is not finite after the step"."""


class LoopError(Error, ValueError):
    """A loop file or loop set that cannot be used (scandyn.load_loops, scandyn.parse_loops):
    JSON that is not the schema, an unknown link, a loop between a link and itself, loops
    made for another model. The message names the file (or "<text>"), the loop and the key."""
