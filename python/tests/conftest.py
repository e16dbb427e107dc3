"""Shared fixtures of the Python package's tests (run by scripts/test.sh; docs/python.md).

The package under test is whatever `import scandyn` finds: the build tree's
(PYTHONPATH=<build>/python, as scripts/test.sh runs it) or an installed one.
The command-line comparisons need the `scandyn` program: $SCANDYN_CLI, else
build/scandyn or build-py/scandyn in the checkout; without it they skip."""

import os
import shutil
import subprocess

import numpy as np
import pytest

import scandyn as sd

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# Models every engine test runs on: a 7-DoF arm, a 12-DoF tree (quadruped), a chain
MODELS = ["iiwa", "hyq", "rope:20"]
DTYPES = [np.float64, np.float32]


def find_cli():
    cli = os.environ.get("SCANDYN_CLI")
    if cli:
        return cli
    for d in ("build", "build-py"):
        p = os.path.join(ROOT, d, "scandyn")
        if os.access(p, os.X_OK):
            return p
    return shutil.which("scandyn")


@pytest.fixture(scope="session")
def cli():
    p = find_cli()
    if not p:
        pytest.skip("the scandyn command was not found (set SCANDYN_CLI or build build/scandyn)")
    return p


@pytest.fixture(scope="session", params=MODELS)
def model(request):
    return sd.load_model(request.param)


def states(model, batch, dtype, seed=0):
    """Random states: q in [-pi, pi], qd, qdd, tau in [-1, 1]; (batch, nv) each."""
    rng = np.random.default_rng(seed)
    nv = model.nv
    q = rng.uniform(-np.pi, np.pi, (batch, nv)).astype(dtype)
    qd = rng.uniform(-1, 1, (batch, nv)).astype(dtype)
    qdd = rng.uniform(-1, 1, (batch, nv)).astype(dtype)
    tau = rng.uniform(-1, 1, (batch, nv)).astype(dtype)
    return q, qd, qdd, tau


def uniform_states(nv, B, seed=0):
    """Three (B, nv) float64 arrays uniform in [-1, 1]: (q, qd, qdd) or (q, qd, tau)."""
    rng = np.random.default_rng(seed)
    return [rng.uniform(-1, 1, (B, nv)) for _ in range(3)]


def assert_close(got, want, rel):
    """max |got - want| <= rel max(1, max |want|); got: a NumPy array or a torch tensor (any device)."""
    got = got.detach().cpu().numpy() if hasattr(got, "detach") else np.asarray(got)
    err = np.max(np.abs(got - want))
    assert err <= rel * max(1.0, np.max(np.abs(want))), err


def run_cli(cli, model_spec, cols, algo, tmp_path, backend="serial", precision="double", extra=()):
    """Runs `scandyn eval` on the columns {name: (B, nv) array}; returns {column: (B,) float64}."""
    names = []
    arrays = []
    for prefix, a in cols.items():
        a = np.asarray(a, dtype=np.float64)
        for i in range(a.shape[1]):
            names.append(f"{prefix}_{i}")
            arrays.append(a[:, i])
    data = np.stack(arrays, axis=1)
    states_csv = tmp_path / "states.csv"
    out_csv = tmp_path / "out.csv"
    with open(states_csv, "w") as f:
        f.write(",".join(names) + "\n")
        for row in data:
            f.write(",".join(repr(float(x)) for x in row) + "\n")
    cmd = [cli, "eval", "--model", model_spec, "--states", str(states_csv), "--out", str(out_csv),
           "--algo", algo, "--backend", backend, "--precision", precision, *extra]
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    with open(out_csv) as f:
        header = f.readline().strip().split(",")
        rows = [[float(x) for x in line.strip().split(",")] for line in f if line.strip()]
    table = np.array(rows, dtype=np.float64).reshape(len(rows), len(header))
    return {name: table[:, k] for k, name in enumerate(header)}


# One link whose inertia about its joint axis is zero: forward dynamics' articulated
# pivot is 0 (a model loaded with allow_nonphysical_inertia=True).
DEGENERATE_URDF = """<robot name="degenerate">
  <link name="base"/>
  <link name="a"><inertial><mass value="1"/><origin xyz="0 0 0"/>
    <inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/></inertial></link>
  <joint name="j" type="continuous"><parent link="base"/><child link="a"/><axis xyz="0 0 1"/></joint>
</robot>"""


def degenerate_urdf(tmp_path):
    """The path of DEGENERATE_URDF written into tmp_path."""
    urdf = tmp_path / "degenerate.urdf"
    urdf.write_text(DEGENERATE_URDF)
    return urdf
