"""The robot models shipped with scandyn (iiwa, hyq, atlas: URDF files installed with
the package). ``scandyn.models.path("iiwa")`` is the file's path; ``load_model("iiwa")``
finds it by name."""

import os as _os

_HERE = _os.path.dirname(_os.path.abspath(__file__))


def directory():
    """The directory holding the shipped URDF files (of this installed package)."""
    return _HERE


def names():
    """The shipped models' names, e.g. ['atlas', 'hyq', 'iiwa']."""
    return sorted(f[:-5] for f in _os.listdir(_HERE) if f.endswith(".urdf"))


def path(name):
    """The path of the shipped model ``name`` ("iiwa" or "iiwa.urdf")."""
    file = name if name.endswith(".urdf") else name + ".urdf"
    p = _os.path.join(_HERE, file)
    if not _os.path.isfile(p):
        from ..errors import ModelError

        raise ModelError(
            f"no shipped model named {name!r} in {_HERE} (shipped: {', '.join(names()) or 'none'})"
        )
    return p
