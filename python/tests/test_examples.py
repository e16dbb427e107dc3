"""The examples run: examples/quickstart.py (NumPy; its environment part needs gymnasium)
and, where torch is installed, a short run of examples/train_swingup_es.py (its return
check is the example's own; here only that it runs, with the gain check waived)."""

import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def run(*args):
    import scandyn

    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [os.path.dirname(os.path.dirname(scandyn.__file__)), os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)


def test_quickstart():
    r = run("examples/quickstart.py")
    assert r.returncode == 0, r.stderr
    assert "iiwa" in r.stdout and "scandyn.Simulator(" in r.stdout


def test_training_example_runs():
    pytest.importorskip("torch", reason="torch is not installed (not needed in CI)")
    pytest.importorskip("gymnasium", reason="gymnasium is not installed")
    r = run("examples/train_swingup_es.py", "--iters", "2", "--envs", "8", "--steps", "20", "--min-gain=-1e9")
    assert r.returncode == 0, r.stderr
    assert "iter   2: population return" in r.stdout and "OK" in r.stdout
