"""Loading a URDF after torch / JAX / CuPy were imported (each in a fresh interpreter,
so a crash is a failed test with its output, not a dead test run). On the GPU machine
pytest once died with SIGSEGV inside load_model after such imports; the module now
exports nothing but its init function and binds its own symbols (python/CMakeLists.txt)."""

import importlib.util
import os
import subprocess
import sys

import pytest

LIBS = ["torch", "jax", "cupy"]

SCRIPT = """
import {lib}
{extra}
import numpy as np, scandyn as sd
m = sd.load_model("iiwa")
assert m.nv == 7
q = np.zeros((3, 7))
sd.inverse_dynamics(m, q, q, q)
print("ok", sd.load_model("hyq").nv)
"""


@pytest.mark.parametrize("lib", LIBS)
def test_load_urdf_after_import(lib):
    if importlib.util.find_spec(lib) is None:
        pytest.skip(f"{lib} is not installed")
    extra = {"torch": "torch.zeros(1)", "jax": "jax.numpy.zeros(1).block_until_ready()", "cupy": ""}[lib]
    r = subprocess.run([sys.executable, "-c", SCRIPT.format(lib=lib, extra=extra)], capture_output=True, text=True,
                       env=dict(os.environ), timeout=300)
    assert r.returncode == 0 and "ok 12" in r.stdout, (
        f"exit {r.returncode} loading a URDF after import {lib}\nstdout:\n{r.stdout}\nstderr:\n{r.stderr[-4000:]}")
