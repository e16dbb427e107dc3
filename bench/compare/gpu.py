#!/usr/bin/env python3
"""GPU side by side: scandyn CUDA against MuJoCo Warp, MJX and GRiD (bench/compare/gpu.sh runs it).

Each (library, model) pair runs in a worker subprocess with its own time limit, so a peer that
hangs, runs out of memory or takes too long to compile is recorded (note column) and the run
goes on; a global deadline (--deadline, seconds since the start of gpu.sh) skips what no longer
fits, again with a row saying so. Rows are appended to --out as they come.

Per model: the double serial reference (`scandyn eval`) on CHECK_STATES random states, then per
library the equality check on those states and the timings (float32, the precision every peer
computes in; scandyn's `bench` rows for id, bias, mass and fd: the engine's strategy (`thread`,
`scan-local`, `crba_thread`, `crba_block`, `aba_thread`, ...) with the batch resident in device
memory, and the same with `-host`: host buffers, copies included). With --scandyn-via module,
scandyn's rows come from the Python package instead (scandyn_peer.py: the engines on torch
CUDA tensors, strategy `<engine strategy>-py`, checked on the same states), run as a worker
like the peers; the installed package (pip install .) must be importable.
"""
import argparse
import json
import os
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402
from common import Model, log  # noqa: E402

ROBOTS = ['iiwa', 'hyq', 'atlas']
ROPES = ['rope:10', 'rope:100', 'rope:1000', 'rope:10000', 'rope:100000']
START = float(os.environ.get('SCANDYN_COMPARE_START', time.time()))


def left(args):
    return args.deadline - (time.time() - START)


def algos_for(nv):
    # the nv x nv mass matrix beyond 1000 DoF is 8 MB+ per instance and state: not compared;
    # dfd (dqdd/dq, dqdd/dqd: scandyn's fd derivatives, GRiD's forward_dynamics_gradient) on
    # the robots only (scandyn's CUDA engine: one thread per instance up to 64 DoF)
    return ['id', 'bias', 'fd'] + (['mass'] if nv <= 1000 else []) + (['dfd'] if nv <= 64 else [])


def batches_for(args, name, lib=None):
    if name not in ROBOTS:
        return [1]
    if lib == 'mujoco-mjx':  # one XLA compilation per batch size and algorithm
        return args.mjx_batches
    return args.batches


# ---- worker: one library on one model --------------------------------------------------------------

def worker(args):
    """Runs in a subprocess: check + timings of one library on one model; rows as JSON lines on stdout."""
    model = Model(args.model, args.workdir)
    names = common.scandyn_joints(args.scandyn, model)
    nv = len(names)
    S = common.random_states(nv)
    ref = np.load(args.ref)
    ref = {k: ref[k] for k in ref.files}
    algos = [a for a in algos_for(nv) if a in args.algos.split(',') and (a != 'dfd' or args.library == 'grid')]

    def emit(**kw):
        print('ROW ' + json.dumps(kw), flush=True)

    lib = args.library
    BK = 'cuda' if args.device.startswith('cuda') else args.device  # noqa: N806
    if lib == 'grid':
        import grid_peer
        # the build's batch limit covers the timed batches and the check's CHECK_STATES states
        R = grid_peer.GridRunner(cache_dir=args.grid_cache, algos=algos,
                                 max_batch=max(batches_for(args, args.model) + [common.CHECK_STATES]),
                                 cuda_arch=int(os.environ['GRID_CUDA_ARCH']) if os.environ.get('GRID_CUDA_ARCH') else None)
        t = time.time()
        errs = grid_peer.check(R, model, names, ref, S, algos)
        log('grid: %s built/loaded in %.0f s' % (args.model, time.time() - t))

        def prep(a, b):
            R.prepare(a, b, nv=nv)
        timed = lambda: grid_peer.timed(R, args.min_time)  # noqa: E731
    elif lib == 'scandyn':
        import scandyn_peer
        R = scandyn_peer.ScandynRunner(model, args.device if args.device.startswith('cuda') else 'cuda:0')
        errs = scandyn_peer.check(R, ref, S, algos)
        prep = R.prepare
        timed = lambda: common.timed(R.call, R.sync, args.min_time)  # noqa: E731
    else:
        import mujoco_peer
        R = (mujoco_peer.MjxRunner(args.device, args.mjx_matmul_precision) if lib == 'mujoco-mjx'
             else mujoco_peer.WarpRunner(args.device))
        errs, mjm = mujoco_peer.check(R, model, names, ref, S, algos)

        def prep(a, b):
            R.prepare(mjm, a, b)
        timed = lambda: mujoco_peer.timed(R.call, R.sync, args.min_time)  # noqa: E731
    log('check %s %s: %s' % (lib, args.model, '  '.join('%s %.1e' % kv for kv in errs.items())))
    for a in algos:
        for b in batches_for(args, args.model, lib):
            t0 = time.time()
            try:
                prep(a, b)
                spc = timed()
                emit(algo=a, strategy=R.strategy,
                     backend=BK, precision='float', model=args.model, links=nv, instances=b, seconds_per_call=spc,
                     library=lib, version=R.version, check_max_err=errs[a])
            except Exception as e:  # noqa: BLE001
                emit(algo=a, backend=BK, precision='float', model=args.model, links=nv, instances=b, library=lib,
                     version=getattr(R, 'version', ''), check_max_err=errs.get(a, ''),
                     note='failed: %s: %s' % (type(e).__name__, str(e).splitlines()[0][:200] if str(e) else ''))
                break  # larger batches will not do better
            if time.time() - t0 > args.slow:
                emit(algo=a, backend=BK, precision='float', model=args.model, links=nv, library=lib,
                     version=R.version, note='skipped larger batches: batch %d took %.0f s to set up and time' % (b, time.time() - t0))
                break


# ---- driver ---------------------------------------------------------------------------------------

def scandyn_rows(args, rows, model, nv, S_csv, ref):
    """scandyn cuda: the check (eval --backend cuda) and the timings (bench --backend cuda);
    with --scandyn-via module the main loop runs the Python package as a worker instead."""
    if args.scandyn_via == 'module':
        return
    version = args.scandyn_version
    algos = [a for a in algos_for(nv) if a in args.algos.split(',')]
    # mass (nv x nv per state, both triangles, scandyn's DoF order) up to 1000 DoF as algos_for says;
    # checked like the others against the double serial reference, whose M the peers are checked on
    # fd on the GPU: chains (the ropes) at any length through the parallel chain forward dynamics
    # (CudaForwardDynamics Auto); trees beyond 1000 DoF would take the dense JSI, nv^2 per instance
    cuda_algos = [a for a in algos if not (a == 'fd' and nv > 1000 and not model.name.startswith('rope:'))]
    errs = {}
    for prec in ('float', 'double'):
        with tempfile.TemporaryDirectory() as tmp:
            try:
                out = common.scandyn_eval(args.scandyn, model, S_csv, os.path.join(tmp, 'o.csv'), algos=cuda_algos,
                                          backend='cuda', precision=prec)
                got = common.read_outputs(out, nv)
                errs[prec] = {a: common.rel_err(got[a], ref[a]) for a in cuda_algos}
            except subprocess.CalledProcessError as e:
                errs[prec] = {}
                log('scandyn cuda eval failed: %s' % (e.stderr or '').strip()[-300:])
    log('check scandyn cuda %s: %s' % (model.name, errs))
    if 'fd' in algos and 'fd' not in cuda_algos:
        rows.add(algo='fd', backend='cuda', precision='float', model=model.name, links=nv, library='scandyn',
                 version=version, note='not run: scandyn cuda fd beyond 1000 DoF on a tree is the dense JSI (nv^2 per instance)')
    for a in cuda_algos:
        for prec in ('float',) + (('double',) if a == 'id' else ()):
            for b in batches_for(args, model.name):
                if left(args) < 20:
                    rows.add(algo=a, backend='cuda', precision=prec, model=model.name, links=nv, instances=b,
                             library='scandyn', version=version, note='skipped: time budget')
                    continue
                cmd = [args.scandyn, 'bench'] + model.scandyn_args() + [
                    '--algo', a, '--instances', str(b), '--backend', 'cuda', '--precision', prec,
                    '--min-time', str(args.min_time)]
                r = subprocess.run(cmd, capture_output=True, text=True, timeout=max(10, min(300, left(args))))
                parsed = common.parse_bench_rows(r.stdout)
                if r.returncode != 0 or not parsed:
                    rows.add(algo=a, backend='cuda', precision=prec, model=model.name, links=nv, instances=b,
                             library='scandyn', version=version,
                             note='failed: %s' % (r.stderr.strip().splitlines() or ['exit %d' % r.returncode])[-1][:200])
                    break
                for row in parsed:
                    row['model'] = model.name
                    rows.add(library='scandyn', version=version, check_max_err=errs.get(prec, {}).get(a, ''), **row)


def run_worker(args, rows, lib, model, nv, ref_npz, limit):
    cmd = [sys.executable, os.path.abspath(__file__), '--worker', '--library', lib, '--model', model.name,
           '--scandyn', args.scandyn, '--ref', ref_npz, '--workdir', args.workdir, '--device', args.warp_device,
           '--min-time', str(args.min_time), '--batches', ','.join(map(str, args.batches)), '--algos', args.algos,
           '--mjx-batches', ','.join(map(str, args.mjx_batches)), '--mjx-matmul-precision', args.mjx_matmul_precision,
           '--slow', str(args.slow), '--grid-cache', args.grid_cache]
    got = 0
    t0 = time.time()
    with open(os.path.join(args.logdir, 'worker-%s-%s.log' % (lib, model.name.replace(':', ''))), 'w') as logf:
        # its own process group: a time limit stops the worker and what it started (nvcc, ...)
        p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=logf, text=True, start_new_session=True)
        lines = queue.Queue()
        reader = threading.Thread(target=lambda: ([lines.put(l) for l in p.stdout], lines.put(None)), daemon=True)
        reader.start()
        try:
            while True:
                remaining = limit - (time.time() - t0)
                if remaining <= 0:
                    raise subprocess.TimeoutExpired(cmd, limit)
                try:
                    line = lines.get(timeout=min(remaining, 5))
                except queue.Empty:
                    continue
                if line is None:
                    break
                logf.write(line)
                logf.flush()
                if line.startswith('ROW '):
                    rows.add(**json.loads(line[4:]))
                    got += 1
            p.wait(timeout=max(1, limit - (time.time() - t0)))
        except subprocess.TimeoutExpired:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            p.wait()
            rows.add(backend='cuda', precision='float', model=model.name, links=nv, library=lib,
                     note='stopped after %.0f s (its time limit): %s' % (time.time() - t0,
                          'no row yet (build, load or check still running)' if not got else 'later rows missing'))
            return False
    if p.returncode != 0:
        tail = open(logf.name).read().strip().splitlines()
        why = next((l for l in reversed(tail) if 'Error' in l or 'error' in l), tail[-1] if tail else '')
        # a peer's own diagnostic printed before the exception (GRiD: "... failed: out of memory")
        cause = next((l for l in reversed(tail) if 'out of memory' in l.lower() and l != why), '')
        rows.add(backend='cuda', precision='float', model=model.name, links=nv, library=lib,
                 note='failed: %s' % why.strip()[:300] + (' (log: %s)' % cause.strip()[:200] if cause else ''))
        return False
    return got > 0


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--scandyn', required=True)
    ap.add_argument('--out', help='CSV to write (driver)')
    ap.add_argument('--logdir', default='.')
    ap.add_argument('--device', default='h100', help='device name for the CSV (driver); warp device (worker)')
    ap.add_argument('--warp-device', default='cuda:0')
    ap.add_argument('--models', default=','.join(ROBOTS + ROPES))
    ap.add_argument('--peers', default='mujoco-warp,mujoco-mjx,grid')
    ap.add_argument('--scandyn-via', choices=('command', 'module'), default='command',
                    help="scandyn's rows from the command (bench --backend cuda) or from the Python package "
                         "(scandyn_peer.py: engines on torch CUDA tensors)")
    ap.add_argument('--algos', default='id,bias,mass,fd')
    ap.add_argument('--batches', default='1,100,10000,1000000')
    ap.add_argument('--mjx-batches', default='1000000')
    ap.add_argument('--mjx-matmul-precision', default='',
                    help="JAX's jax_default_matmul_precision for MJX: '' keeps JAX's default (TF32 products on "
                         "Ampere and newer GPUs), 'highest' computes float32 products (strategy jit-vmap-highest)"),
    ap.add_argument('--min-time', type=float, default=0.2)
    ap.add_argument('--deadline', type=float, default=540, help='seconds after gpu.sh started')
    ap.add_argument('--peer-limit', type=float, default=120, help='seconds per peer and model (GRiD twice that)')
    ap.add_argument('--slow', type=float, default=40, help='a batch taking longer than this stops larger ones')
    ap.add_argument('--workdir', default=None)
    ap.add_argument('--grid-cache', default=os.environ.get('GRID_RBD_CACHE_DIR', '/tmp/grid-cache'))
    # worker
    ap.add_argument('--worker', action='store_true')
    ap.add_argument('--library')
    ap.add_argument('--model')
    ap.add_argument('--ref')
    args = ap.parse_args()
    args.batches = [int(float(x)) for x in args.batches.split(',')]
    args.mjx_batches = [int(float(x)) for x in args.mjx_batches.split(',')]
    if args.worker:
        args.device = args.device
        return worker(args)
    args.workdir = args.workdir or os.path.join(args.logdir, 'models')
    os.makedirs(args.workdir, exist_ok=True)
    args.scandyn_version = 'scandyn ' + subprocess.run([args.scandyn, '--version'], capture_output=True,
                                          text=True).stdout.strip().split()[-1]
    commit = subprocess.run(['git', '-C', common.REPO, 'rev-parse', '--short', 'HEAD'], capture_output=True,
                            text=True).stdout.strip()
    args.scandyn_version += ('+' + commit) if commit else ''
    rows = common.Rows(args.out)
    peers = [p for p in args.peers.split(',') if p]
    missing = {}
    for p, mod in (('mujoco-warp', 'mujoco_warp'), ('mujoco-mjx', 'mujoco.mjx'), ('grid', 'grid_rbd')):
        if p in peers:
            r = subprocess.run([sys.executable, '-c', 'import %s' % mod], capture_output=True, text=True)
            if r.returncode != 0:
                missing[p] = (r.stderr.strip().splitlines() or ['import failed'])[-1]
                log('%s: not importable: %s' % (p, missing[p]))
    if args.scandyn_via == 'module':
        r = subprocess.run([sys.executable, '-c', 'import scandyn, torch'], capture_output=True, text=True)
        if r.returncode != 0:
            missing['scandyn'] = (r.stderr.strip().splitlines() or ['import failed'])[-1]
            log('scandyn module: not importable: %s' % missing['scandyn'])
    # The order fits the most into one 10-minute command: scandyn on the robots, MuJoCo Warp,
    # GRiD on iiwa (it compiles CUDA per robot, a minute or more each), MJX (an XLA compilation
    # per computation and batch size), GRiD on the other robots, then the ropes in the same
    # order. A peer that failed or ran out of time on a rope is not tried on longer ones.
    models = args.models.split(',')
    robots, ropes = [m for m in models if m in ROBOTS], [m for m in models if m not in ROBOTS]
    schedule = []
    for group in (robots, ropes):
        first_robot = group[:1] if group is robots else group
        schedule += [(m, 'scandyn') for m in group]
        schedule += [(m, 'mujoco-warp') for m in group]
        schedule += [(m, 'grid') for m in first_robot]
        schedule += [(m, 'mujoco-mjx') for m in group]
        schedule += [(m, 'grid') for m in group if m not in first_robot]
    refs, gave_up = {}, {}
    for name, p in schedule:
        if p != 'scandyn' and p not in peers:
            continue
        model = Model(name, args.workdir)
        if name not in refs:
            names = common.scandyn_joints(args.scandyn, model)
            nv = len(names)
            S = common.random_states(nv)
            with tempfile.TemporaryDirectory() as tmp:
                s_csv = os.path.join(tmp, 'states.csv')
                common.write_states(s_csv, S)
                algos = [a for a in algos_for(nv) if a in args.algos.split(',')]
                ref = common.read_outputs(common.scandyn_eval(args.scandyn, model, s_csv,
                                                              os.path.join(tmp, 'ref.csv'), algos=algos), nv)
                ref_npz = os.path.join(args.workdir, 'ref-%s.npz' % name.replace(':', ''))
                np.savez(ref_npz, **ref)
                refs[name] = (nv, ref_npz)
                scandyn_rows(args, rows, model, nv, s_csv, ref)
        if p == 'scandyn' and args.scandyn_via == 'command':
            continue
        nv, ref_npz = refs[name]
        if p in missing:
            rows.add(backend='cuda', precision='float', model=name, links=nv, library=p,
                     note='not installed: %s' % missing[p])
            continue
        if p in gave_up and name not in ROBOTS:
            rows.add(backend='cuda', precision='float', model=name, links=nv, library=p,
                     note='not tried: %s already failed or ran out of time on %s' % (p, gave_up[p]))
            continue
        # every peer compiles per model (GRiD: CUDA code; MJX: one XLA program per computation and
        # batch size; MuJoCo Warp: kernels per tree level), ropes included: the same limit for both
        limit = min(args.peer_limit * (2 if p == 'grid' else 1), left(args))
        if limit < 15:
            rows.add(backend='cuda', precision='float', model=name, links=nv, library=p,
                     note='skipped: time budget of this run spent')
            continue
        if not run_worker(args, rows, p, model, nv, ref_npz, limit) and name not in ROBOTS:
            gave_up[p] = name
    log('wrote %s (%d rows)' % (args.out, len(rows.rows)))


if __name__ == '__main__':
    main()
