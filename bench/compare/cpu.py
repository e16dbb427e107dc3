#!/usr/bin/env python3
"""CPU side by side: scandyn (serial, OpenMP) against Pinocchio (C++, from the `pin` wheel).

Run through bench/compare/cpu.sh, which builds both programs. For each model:
  1. the equality check: CHECK_STATES random states through `scandyn eval` (serial double,
     and openmp double) and `pin_bench eval` (Pinocchio's rnea, nonLinearEffects, crba, aba);
     DoF orders are matched by joint name (they agree for these URDFs: both sort siblings by
     joint name); only joint-space quantities are compared, so Pinocchio's [linear; angular]
     spatial order never enters;
  2. timing: `scandyn bench` and `pin_bench bench` for every algorithm and batch size, serial
     and (for batches) OpenMP on all cores.
Writes the rows to --out as they come (columns: bench/compare/common.py).
"""
import argparse
import os
import resource
import platform
import subprocess
import sys
import tempfile

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402
from common import Model, Rows, log  # noqa: E402

DEFAULT_MODELS = 'iiwa,hyq,atlas,rope:100,rope:1000'


PIN_MEMORY_LIMIT = 6 << 30  # bytes of address space for pin_bench: a model too large fails, not the machine


def limit_memory():
    resource.setrlimit(resource.RLIMIT_AS, (PIN_MEMORY_LIMIT, PIN_MEMORY_LIMIT))


def pin_failure(stderr):
    """pin_bench's error, with what it means when it ran out of memory."""
    msg = (stderr or '').strip().splitlines()[-1] if (stderr or '').strip() else 'no message'
    if 'bad_alloc' in msg or 'memory' in msg.lower():
        msg = ('pinocchio::Data does not fit in %d GiB (its size grows as nv^3 on a chain: 52 MB at 100 links, '
               '0.28 GB at 200, 2.1 GB at 400): %s' % (PIN_MEMORY_LIMIT >> 30, msg))
    return msg


def pin_info(pin_bench, model):
    out = subprocess.run([pin_bench, 'info', '--urdf', model.urdf], check=True, capture_output=True,
                         text=True).stdout.splitlines()
    return [l.split()[1] for l in out[1:]]


def check(args, model, tmp):
    """-> {(library, backend): {algo: err}} and the DoF permutation."""
    names = common.scandyn_joints(args.scandyn, model)
    pnames = pin_info(args.pin_bench, model)
    if sorted(names) != sorted(pnames):
        raise RuntimeError('%s: scandyn and pinocchio joints differ' % model.name)
    pos = {n: i for i, n in enumerate(pnames)}
    P = np.array([pos[n] for n in names])  # scandyn DoF k is Pinocchio DoF P[k]
    nv = len(names)
    S = common.random_states(nv)
    s_csv = os.path.join(tmp, 'states.csv')
    common.write_states(s_csv, S)
    Sp = {k: np.empty_like(v) for k, v in S.items()}
    for k in S:
        Sp[k][:, P] = S[k]
    p_csv = os.path.join(tmp, 'states_pin.csv')
    common.write_states(p_csv, Sp)
    ref = common.read_outputs(common.scandyn_eval(args.scandyn, model, s_csv, os.path.join(tmp, 'ref.csv')), nv)
    r = subprocess.run([args.pin_bench, 'eval', '--urdf', model.urdf, '--states', p_csv, '--out',
                        os.path.join(tmp, 'pin.csv')], capture_output=True, text=True, preexec_fn=limit_memory)
    errs = {('pinocchio', 'serial'): {}, ('scandyn', 'serial'): {}, ('scandyn', 'openmp'): {}}
    if r.returncode != 0:
        fail = pin_failure(r.stderr)
        log('check %s: pinocchio failed: %s' % (model.name, fail))
        errs[('pinocchio', 'openmp')] = errs[('pinocchio', 'serial')]
        return errs, nv, fail
    pin = common.read_outputs(os.path.join(tmp, 'pin.csv'), nv)
    pin = {a: (v[:, P][:, :, P] if a == 'mass' else v[:, P]) for a, v in pin.items()}
    omp = common.read_outputs(common.scandyn_eval(args.scandyn, model, s_csv, os.path.join(tmp, 'omp.csv'),
                                                  backend='openmp'), nv)
    for a in common.ALGOS:
        errs[('pinocchio', 'serial')][a] = common.rel_err(pin[a], ref[a])
        errs[('scandyn', 'serial')][a] = common.rel_err(ref[a], pin[a])
        errs[('scandyn', 'openmp')][a] = common.rel_err(omp[a], pin[a])
    errs[('pinocchio', 'openmp')] = errs[('pinocchio', 'serial')]  # same functions per instance
    log('check %s (nv %d, %d states; scandyn order %s pinocchio order): %s' % (
        model.name, nv, common.CHECK_STATES, '==' if list(P) == list(range(nv)) else '!=',
        '  '.join('%s %.1e' % (a, errs[('pinocchio', 'serial')][a]) for a in common.ALGOS)))
    return errs, nv, None


def batches_for(args, nv, algo):
    out = []
    for b in args.batches:
        work = b * nv * (nv if algo == 'mass' else 1)
        if b == 1 or work <= args.max_work:
            out.append(b)
    return out


def run(cmd, timeout):
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    if r.returncode != 0:
        raise RuntimeError((r.stderr or r.stdout).strip().splitlines()[-1] if (r.stderr or r.stdout).strip()
                           else 'exit %d' % r.returncode)
    return r.stdout


def time_config(args, rows, model, nv, algo, b, backend, errs, pin_fail, sc_version, libs):
    """One configuration for every library: --repeat runs of each, interleaved (scandyn,
    pinocchio, pinocchio-hdr, scandyn, ...) so that a change of load on a shared machine hits
    all of them alike; the fastest run of each is its row."""
    name = model.name
    runners = []  # (key, command, memory limit)
    cmd = [args.scandyn, 'bench'] + model.scandyn_args() + [
        '--algo', algo, '--instances', str(b), '--backend', backend, '--min-time', str(args.min_time)]
    if backend == 'openmp':
        cmd += ['--threads', str(args.threads)]
    runners.append(('scandyn', cmd, None))
    for lib, exe, ver in libs:
        suffix = '' if exe == args.pin_bench else '-hdr'
        if pin_fail:
            rows.add(algo=algo, strategy=('pool' if backend == 'openmp' and algo in ('id', 'fd') else
                                          'omp-loop' if backend == 'openmp' else 'loop') + suffix,
                     backend=backend, precision='double', model=name, links=nv, instances=b,
                     library=lib, version=ver, note='failed: %s' % pin_fail)
            continue
        pcmd = [exe, 'bench', '--urdf', model.urdf, '--name', name, '--algo', algo, '--instances', str(b),
                '--min-time', str(args.min_time)]
        if backend == 'openmp':
            pcmd += ['--threads', str(args.threads)]
        runners.append(((lib, ver, suffix), pcmd, limit_memory))
    best, failed = {}, {}
    for _ in range(args.repeat):
        for key, c, pre in runners:
            if key in failed:
                continue
            try:
                r = subprocess.run(c, capture_output=True, text=True, timeout=600, preexec_fn=pre)
                if r.returncode != 0:
                    raise RuntimeError(pin_failure(r.stderr) if pre else
                                       (r.stderr.strip().splitlines() or ['exit %d' % r.returncode])[-1])
                if key == 'scandyn':
                    row = common.parse_bench_rows(r.stdout)[0]
                else:
                    f = r.stdout.strip().splitlines()[-1].split(',')
                    row = dict(algo=f[0], strategy=f[1] + key[2], backend=f[2], precision=f[3], links=f[5],
                               instances=f[6], seconds_per_call=f[7], evals_per_second=f[8])
                if key not in best or float(row['seconds_per_call']) < float(best[key]['seconds_per_call']):
                    best[key] = row
            except Exception as e:  # noqa: BLE001
                failed[key] = str(e)
    for key, c, pre in runners:
        lib, ver = ('scandyn', sc_version) if key == 'scandyn' else key[:2]
        chk = errs[(lib, backend)].get(algo, '')
        if key in best:
            row = dict(best[key])
            row['model'] = name
            row['seconds_per_call'] = float(row['seconds_per_call'])
            row['evals_per_second'] = float(row['evals_per_second'])
            rows.add(library=lib, version=ver, check_max_err=chk, **row)
        else:
            rows.add(algo=algo, backend=backend, precision='double', model=name, links=nv, instances=b,
                     library=lib, version=ver, check_max_err=chk, note='failed: %s' % failed.get(key, '?'))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--scandyn', required=True)
    ap.add_argument('--pin-bench', required=True, help='pin_bench (the wheel\'s precompiled Pinocchio)')
    ap.add_argument('--pin-bench-hdr', help='pin_bench_hdr (Pinocchio\'s templates compiled here); optional')
    ap.add_argument('--out', required=True)
    ap.add_argument('--device', required=True)
    ap.add_argument('--models', default=DEFAULT_MODELS)
    ap.add_argument('--algos', default='id,bias,mass,fd')
    ap.add_argument('--batches', default='1,100,10000')
    ap.add_argument('--max-work', type=float, default=2e6,
                    help='skip batches with instances x DoF (x DoF for mass) above this (batch 1 always runs)')
    ap.add_argument('--threads', type=int, default=os.cpu_count())
    ap.add_argument('--min-time', type=float, default=0.2)
    ap.add_argument('--repeat', type=int, default=3, help='runs of each timing, interleaved; the fastest counts')
    ap.add_argument('--check-only', action='store_true')
    args = ap.parse_args()
    args.batches = [int(x) for x in args.batches.split(',')]
    algos = args.algos.split(',')

    sc_version = 'scandyn ' + run([args.scandyn, '--version'], 30).strip().split()[-1]
    commit = subprocess.run(['git', '-C', common.REPO, 'rev-parse', '--short', 'HEAD'], capture_output=True,
                            text=True).stdout.strip()
    sc_version += ('+' + commit) if commit else ''
    pin_version = run([args.pin_bench, 'version'], 30).split()[1].rstrip(',')
    log('device %s: %s, %d threads for openmp; scandyn %s, pinocchio %s' % (
        args.device, platform.processor() or platform.machine(), args.threads, sc_version, pin_version))

    rows = Rows(args.out)
    libs = [('pinocchio', args.pin_bench, 'pinocchio %s (wheel library)' % pin_version)]
    if args.pin_bench_hdr:
        libs.append(('pinocchio', args.pin_bench_hdr, 'pinocchio %s (headers compiled here)' % pin_version))
    for name in args.models.split(','):
        model = Model(name, os.path.join(tempfile.gettempdir(), 'scandyn-compare-models'))
        with tempfile.TemporaryDirectory() as tmp:
            errs, nv, pin_fail = check(args, model, tmp)
        if args.check_only:
            bad = [a for a in algos if not errs[('pinocchio', 'serial')].get(a, 0) <= 1e-9]
            if bad:
                log('MISMATCH %s: %s' % (name, bad))
                sys.exit(1)
            continue
        for algo in algos:
            for b in batches_for(args, nv, algo):
                for backend in ['serial'] + (['openmp'] if b > 1 else []):
                    time_config(args, rows, model, nv, algo, b, backend, errs, pin_fail, sc_version, libs)
    log('wrote %s (%d rows)' % (args.out, len(rows.rows)))


if __name__ == '__main__':
    main()
