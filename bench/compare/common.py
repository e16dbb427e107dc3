"""Shared pieces of the side-by-side comparison (bench/compare/).

Models, states, the equality check and the CSV rows that cpu.py and gpu.py both use.

CSV columns (bench/results/compare-<device>.csv), DESIGN.md's benchmark columns plus four:
  algo,strategy,backend,precision,model,links,instances,seconds_per_call,evals_per_second,
  max_rel_err,library,version,check_max_err,note
- algo: id (inverse dynamics, RNEA with gravity), bias (h = ID(q, qd, 0)), mass (M(q), CRBA),
  fd (forward dynamics, qdd = M^-1 (tau - h); no contacts, no constraints, no passive forces)
- library / version: who computed the row (scandyn, pinocchio, mujoco-warp, mujoco-mjx, grid)
- max_rel_err: scandyn's own column (its error against its double serial reference, from
  `scandyn bench`); empty for peers
- check_max_err: the equality check of this row's library, precision and backend against
  scandyn's double serial reference on the same random states (CHECK_STATES states, q, qd,
  qdd, tau uniform in [-1, 1]), as max over states of max_i |x_i - ref_i| / max(1, max_i |ref_i|)
  (the same measure as max_rel_err); for scandyn's own rows: scandyn (that backend and
  precision) against the peer's double result where there is one (Pinocchio on the CPU)
- note: empty for a measured row; otherwise why a configuration has no time (a peer that
  cannot be installed, cannot compute it, failed, or was skipped), and the time columns are empty
"""
import csv
import os
import subprocess
import sys
import time

import numpy as np

COLUMNS = ['algo', 'strategy', 'backend', 'precision', 'model', 'links', 'instances', 'seconds_per_call',
           'evals_per_second', 'max_rel_err', 'library', 'version', 'check_max_err', 'note']
ALGOS = ('id', 'bias', 'mass', 'fd')  # compared by every harness
BENCH_ALGOS = ALGOS + ('dfd',)  # rows parse_bench_rows reads (dfd: gpu.py --algos dfd)
CHECK_STATES = 16
HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))


def models_dir():
    d = os.environ.get('SCANDYN_MODELS_DIR')
    if d:
        return d
    return os.path.join(REPO, 'models')  # the shipped robot models


_T0 = time.time()


def log(*a):
    # seconds since this process started: where a run's time goes
    print('[compare +%.0fs]' % (time.time() - _T0), *a, flush=True)
    sys.stdout.flush()


# ---- models ---------------------------------------------------------------------------------------

def rope_urdf(n):
    """scandyn's `rope:N` generator (docs/models.md) as URDF text, for the peers.

    Joint i from link_{i-1} (base for i = 0) at (0,0,0) for i = 0 and (0,0,-0.01) otherwise,
    axis x for even i and y for odd i; each link m = 0.01 kg, COM (0,0,-0.005),
    Ic = diag(m(3r^2+L^2)/12, m(3r^2+L^2)/12, m r^2/2), L = 0.01, r = 0.002. Names are
    zero-padded as scandyn pads them, so the DoF order (joint names sorted) is the index order.
    Joints are `revolute` with wide limits (so Pinocchio gives them nq = 1; the peers'
    limit constraints are disabled)."""
    w = len(str(n - 1))
    m, L, r = 0.01, 0.01, 0.002
    ixx = m * (3 * r * r + L * L) / 12.0
    izz = m * r * r / 2.0
    out = ['<?xml version="1.0"?>', '<robot name="rope%d">' % n, '<link name="base"/>']
    for i in range(n):
        out.append('<link name="link_%0*d"><inertial><origin xyz="0 0 -0.005" rpy="0 0 0"/>'
                   '<mass value="%r"/><inertia ixx="%r" ixy="0" ixz="0" iyy="%r" iyz="0" izz="%r"/>'
                   '</inertial></link>' % (w, i, m, ixx, ixx, izz))
    for i in range(n):
        parent = 'base' if i == 0 else 'link_%0*d' % (w, i - 1)
        z = '0' if i == 0 else '-0.01'
        axis = '1 0 0' if i % 2 == 0 else '0 1 0'
        out.append('<joint name="joint_%0*d" type="revolute"><parent link="%s"/><child link="link_%0*d"/>'
                   '<origin xyz="0 0 %s" rpy="0 0 0"/><axis xyz="%s"/>'
                   '<limit lower="-1e3" upper="1e3" effort="1e6" velocity="1e6"/></joint>'
                   % (w, i, parent, w, i, z, axis))
    out.append('</robot>')
    return '\n'.join(out) + '\n'


class Model:
    """A model by name: `iiwa`, `hyq`, `atlas` (URDFs in the models directory) or `rope:N`."""

    def __init__(self, name, workdir):
        self.name = name
        if name.startswith('rope:'):
            n = int(name.split(':')[1])
            self.spec = name  # what scandyn is given
            self.urdf = os.path.join(workdir, 'rope%d.urdf' % n)  # what the peers are given
            if not os.path.exists(self.urdf):
                os.makedirs(workdir, exist_ok=True)
                with open(self.urdf, 'w') as fh:
                    fh.write(rope_urdf(n))
        else:
            self.urdf = os.path.join(models_dir(), name + '.urdf')
            if not os.path.exists(self.urdf):
                raise FileNotFoundError(self.urdf)
            self.spec = self.urdf
        self.nonphysical = name == 'atlas'  # GRiD's atlas.urdf (docs/models.md)

    def scandyn_args(self):
        return ['--model', self.spec] + (['--allow-nonphysical-inertia'] if self.nonphysical else [])


def scandyn_joints(scandyn, model):
    """Joint names in scandyn's DoF order, from `scandyn info`."""
    out = subprocess.run([scandyn, 'info'] + model.scandyn_args(), check=True, capture_output=True,
                         text=True).stdout
    lines = out.splitlines()
    start = next(i for i, l in enumerate(lines) if l.startswith('index'))
    names = []
    for l in lines[start + 1:]:
        if not l.strip():  # the DoF table ends at a blank line (the frames follow)
            break
        names.append(l.split()[1])
    return names


# ---- states and the check -----------------------------------------------------------------------

def random_states(nv, n=CHECK_STATES, seed=2026):
    rng = np.random.default_rng(seed + nv)
    return {k: rng.uniform(-1.0, 1.0, (n, nv)) for k in ('q', 'qd', 'qdd', 'tau')}


def write_states(path, S):
    nv = S['q'].shape[1]
    with open(path, 'w', newline='') as fh:
        w = csv.writer(fh)
        w.writerow(['%s_%d' % (k, i) for k in ('q', 'qd', 'qdd', 'tau') for i in range(nv)])
        for r in range(S['q'].shape[0]):
            w.writerow(['%.17g' % x for k in ('q', 'qd', 'qdd', 'tau') for x in S[k][r]])


def read_outputs(path, nv):
    """scandyn's OUT.csv columns -> {'id': (n, nv), 'fd': (n, nv), 'mass': (n, nv, nv), 'bias': (n, nv),
    'dfd': (n, nv, 2 nv): [dqdd/dq | dqdd/dqd] per state, the layout GRiD's forward_dynamics_gradient returns}."""
    with open(path) as fh:
        header = fh.readline().strip().split(',')
        data = np.array([np.array(line.split(','), dtype=np.float64) for line in fh if line.strip()]).reshape(-1, len(header))
    col = {c: i for i, c in enumerate(header)}
    out = {}
    # a family's column names are built only when its first column is there (mass of rope:10^4 would be 10^8 names)
    fams = {'id': 'tau_id_{0}', 'fd': 'qdd_fd_{0}', 'mass': 'M_{0}_{1}', 'bias': 'h_{0}'}
    for a, name in fams.items():
        if name.format(0, 0) in col:
            cols = range(nv) if a == 'mass' else [0]  # M's second index; the vectors have one
            x = data[:, [col[name.format(i, j)] for i in range(nv) for j in cols]]
            out[a] = x.reshape(len(data), nv, nv) if a == 'mass' else x
    if 'dqdd_dq_0_0' in col:
        blocks = [data[:, [col['%s_%d_%d' % (b, i, j)] for i in range(nv) for j in range(nv)]].reshape(len(data), nv, nv)
                  for b in ('dqdd_dq', 'dqdd_dqd')]
        out['dfd'] = np.concatenate(blocks, axis=2)
    return out


def scandyn_eval(scandyn, model, states_csv, out_csv, algos=('id', 'fd', 'mass', 'bias'), backend='serial',
                 precision='double'):
    cmd = [scandyn, 'eval'] + model.scandyn_args() + ['--states', states_csv, '--out', out_csv, '--algo',
                                                      ','.join(algos), '--backend', backend, '--precision', precision]
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    return out_csv


def rel_err(x, ref):
    """max over states of max_i |x_i - ref_i| / max(1, max_i |ref_i|) (nan if any x is not finite)."""
    x = np.asarray(x, dtype=np.float64).reshape(len(ref), -1)
    ref = np.asarray(ref, dtype=np.float64).reshape(len(ref), -1)
    if not np.all(np.isfinite(x)):
        return float('nan')
    e = np.max(np.abs(x - ref), axis=1) / np.maximum(1.0, np.max(np.abs(ref), axis=1))
    return float(np.max(e))


def fmt(x):
    if x is None or x == '':
        return ''
    if isinstance(x, float):
        return '%.6g' % x
    return str(x)


class Rows:
    """Collects rows and rewrites the CSV after each, so a run cut short keeps what it measured."""

    def __init__(self, path):
        self.path = path
        self.rows = []

    def add(self, **kw):
        row = {c: fmt(kw.get(c, '')) for c in COLUMNS}
        if row['seconds_per_call'] and not row['evals_per_second']:
            row['evals_per_second'] = fmt(float(kw['instances']) / float(kw['seconds_per_call']))
        self.rows.append(row)
        self.flush()
        log(','.join(row[c] for c in COLUMNS))

    def flush(self):
        tmp = self.path + '.tmp'
        with open(tmp, 'w', newline='') as fh:
            w = csv.DictWriter(fh, fieldnames=COLUMNS, lineterminator='\n')
            w.writeheader()
            w.writerows(self.rows)
        os.replace(tmp, self.path)


def parse_bench_rows(text):
    """Rows printed by `scandyn bench` (10 columns, no header) -> list of dicts."""
    keys = COLUMNS[:10]
    out = []
    for line in text.splitlines():
        parts = line.strip().split(',')
        if len(parts) == 10 and parts[0] in BENCH_ALGOS:
            out.append(dict(zip(keys, parts)))
    return out


def timed(call, sync, min_time):
    """scandyn bench's procedure: a warm-up call, then rounds (at most doubling) until min_time."""
    call()
    sync()
    calls, round_, t0 = 0, 1, time.perf_counter()
    while True:
        for _ in range(round_):
            call()
        sync()
        calls += round_
        el = time.perf_counter() - t0
        if el >= min_time:
            return el / calls
        per = el / calls
        round_ = max(1, min(calls, int((min_time - el) / per) + 1))
