"""`python -m scandyn` is the scandyn command: the same output, files and exit codes as
the program (docs/cli.md) for info, eval, bench and rollout."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import scandyn as sd
from scandyn.__main__ import cli_path
from conftest import states


def run(*args, **kw):
    return subprocess.run([sys.executable, "-m", "scandyn", *args], capture_output=True, text=True, timeout=300,
                          **kw)


def test_version_and_help():
    r = run("--version")
    assert r.returncode == 0 and r.stdout.strip() == f"scandyn {sd.__version__}"
    r = run("--help")
    assert r.returncode == 0 and "info" in r.stdout and "rollout" in r.stdout
    assert os.access(cli_path(), os.X_OK)


def test_info_same_as_program():
    r = run("info", "--model", "iiwa")  # found by name among the package's models
    p = subprocess.run([cli_path(), "info", "--model", sd.models.path("iiwa")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "\nnv       7\n" in r.stdout
    assert r.stdout.splitlines()[0] == p.stdout.splitlines()[0] == "model    iiwa14"
    # the DoF table (index, joint, type, parent, child, axis: up to the blank line) is the program's
    def dof(out):
        lines = out.splitlines()
        start = next(i for i, l in enumerate(lines) if l.startswith("index")) + 1
        end = next((i for i in range(start, len(lines)) if not lines[i].strip()), len(lines))
        return lines[start:end]
    assert len(dof(r.stdout)) == 7 and dof(r.stdout) == dof(p.stdout)
    assert r.stdout == p.stdout.replace(p.stdout.splitlines()[1], r.stdout.splitlines()[1])  # all else alike


def test_eval_matches_module(tmp_path):
    m = sd.load_model("iiwa")
    q, qd, qdd, _ = states(m, 5, np.float64, seed=8)
    names = [f"{p}_{i}" for p in ("q", "qd", "qdd") for i in range(m.nv)]
    data = np.concatenate([q, qd, qdd], axis=1)
    states_csv, out_csv = tmp_path / "s.csv", tmp_path / "o.csv"
    with open(states_csv, "w") as f:
        f.write(",".join(names) + "\n")
        for row in data:
            f.write(",".join(repr(float(x)) for x in row) + "\n")
    r = run("eval", "--model", "iiwa", "--states", str(states_csv), "--out", str(out_csv), "--algo", "id")
    assert r.returncode == 0, r.stderr
    got = np.loadtxt(out_csv, delimiter=",", skiprows=1, ndmin=2)
    np.testing.assert_array_equal(got, sd.inverse_dynamics(m, q, qd, qdd, backend="serial"))


def test_bench_row():
    r = run("bench", "--model", "iiwa", "--algo", "id", "--instances", "16", "--min-time", "0.01")
    assert r.returncode == 0, r.stderr
    row = r.stdout.strip().splitlines()[-1].split(",")
    assert row[0] == "id" and "iiwa" in row[4] and row[6] == "16"


def test_rollout(tmp_path):
    scene = tmp_path / "iiwa64.json"
    scene.write_text(json.dumps({
        "model": sd.models.path("iiwa"), "effects": {"gravity": True, "damping": 0.5}, "integrator": "euler",
        "dt": 0.001, "precision": "double", "backend": "serial", "instances": 64,
        "initial": {"random": {"seed": 1, "q": 0.5, "qd": 0.1}}}))
    out, ref = tmp_path / "t.npy", tmp_path / "ref.npy"
    r = run("rollout", "--scene", str(scene), "--steps", "3", "--out", str(out))
    assert r.returncode == 0, r.stderr
    p = subprocess.run([cli_path(), "rollout", "--scene", str(scene), "--steps", "3", "--out", str(ref)],
                       capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    traj = np.load(out)
    assert traj.shape == (4, 64, 1 + 2 * 7)
    np.testing.assert_array_equal(traj, np.load(ref))


def test_exit_codes():
    r = run("eval", "--model", "iiwa", "--bogus", "1")
    assert r.returncode == 2 and r.stderr.startswith("scandyn: ")
    r = run("info", "--model", "/nonexistent/robot.urdf")
    assert r.returncode == 1 and "robot.urdf" in r.stderr
