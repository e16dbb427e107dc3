#!/usr/bin/env python3
"""Python call overhead: the scandyn package's engines on torch CUDA tensors against the C++
engines' compute_async rows of `scandyn bench --backend cuda` (the batch resident in device
memory), iiwa in float at B = 1, 10^4, 10^6 (the target: at most 10 us per call
above the C++ time).

    python3 bench/python/call_overhead.py --scandyn build-gpu/scandyn --out OUT.csv

Per (algo, B): the C++ row (`scandyn bench ... --backend cuda --precision float`, its
device-resident row: strategy without `-host`) and, in this process, the engine of the
same algorithm (sd.InverseDynamics, ... backend='cuda', float32) on device-resident
torch tensors (column out_layout: a row-major out=, the default call out=None (a new
result per call), and for the mass matrix also out= the entry-major view that is its
default result on CUDA arrays), timed by the same procedure as bench (a warm-up call,
then rounds of calls until --min-time, one torch.cuda.synchronize per round). Two Python
columns: seconds_per_call (back-to-back calls; on the GPU, what the loop sustains) and
host_seconds_per_call (the time a call takes to return, the GPU work queued, not waited
for: the Python layer's own cost). overhead_us = (python - C++) seconds_per_call in us.
Needs a CUDA build of the package installed (pip install .), torch with CUDA, and the
scandyn program of the same tree.
"""
import argparse
import csv
import os
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), 'compare'))
from common import timed  # noqa: E402  bench's procedure, as the comparison's peers are timed

ENGINES = {'id': 'InverseDynamics', 'bias': 'BiasForces', 'mass': 'MassMatrix', 'fd': 'ForwardDynamics'}
INPUTS = {'id': ('q', 'qd', 'qdd'), 'bias': ('q', 'qd'), 'mass': ('q',), 'fd': ('q', 'qd', 'tau')}


def cxx_row(scandyn, model, algo, batch, min_time):
    """The C++ device-resident row of `scandyn bench` (seconds per call, strategy)."""
    cmd = [scandyn, 'bench', '--model', model, '--algo', algo, '--instances', str(batch), '--backend', 'cuda',
           '--precision', 'float', '--min-time', str(min_time)]
    r = subprocess.run(cmd, capture_output=True, text=True, check=True)
    for line in r.stdout.splitlines():
        f = line.split(',')
        if len(f) >= 8 and f[0] == algo and not f[1].endswith('-host') and f[1] != 'strategy':
            return float(f[7]), f[1]
    raise RuntimeError('no device-resident row in: ' + r.stdout)


def host_time(call, sync, calls=200):
    """The time a call takes to return (work queued, not waited for), median of calls."""
    sync()
    ts = []
    for _ in range(calls):
        t = time.perf_counter()
        call()
        ts.append(time.perf_counter() - t)
        sync()
    return float(np.median(ts))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--scandyn', required=True, help='the scandyn program (C++ rows)')
    ap.add_argument('--out', required=True, help='CSV to write')
    ap.add_argument('--model', default='iiwa')
    ap.add_argument('--algos', default='id,bias,mass,fd')
    ap.add_argument('--batches', default='1,10000,1000000')
    ap.add_argument('--min-time', type=float, default=0.5)
    args = ap.parse_args()

    import torch
    import scandyn as sd
    if not torch.cuda.is_available() or sd.backend_unusable('cuda'):
        sys.exit('call_overhead.py: needs torch with CUDA and a CUDA build of scandyn: ' +
                 (sd.backend_unusable('cuda') or 'torch.cuda.is_available() is False'))
    m = sd.load_model(args.model)
    spec = sd.models.path(args.model) if os.path.isfile(os.path.join(sd.models.directory(), args.model + '.urdf')) \
        else args.model
    dev = torch.device('cuda')
    rows = []
    for algo in args.algos.split(','):
        for b in [int(float(x)) for x in args.batches.split(',')]:
            cxx, strategy = cxx_row(args.scandyn, spec, algo, b, args.min_time)
            g = torch.Generator(device=dev).manual_seed(1)
            S = {k: torch.rand(b, m.nv, generator=g, device=dev) * 2 - 1 for k in ('q', 'qd', 'qdd', 'tau')}
            e = getattr(sd, ENGINES[algo])(m, backend='cuda', max_batch=b, dtype=np.float32)
            ins = [S[k] for k in INPUTS[algo]]
            # out= a preallocated row-major array and the default call (out=None: a new
            # result per call, entry-major for the mass matrix); for the mass matrix also
            # out= the entry-major view its default result has (the C++ row's layout)
            outs = [('row-major out=', torch.empty((b, m.nv) + ((m.nv,) if algo == 'mass' else ()), device=dev)),
                    ('default (out=None)', None)]
            if algo == 'mass':
                outs = [('entry-major out=', torch.empty((m.nv, m.nv, b), device=dev).permute(2, 0, 1))] + outs
            for layout, out in outs:

                def call():
                    e(*ins, out=out)
                py = timed(call, torch.cuda.synchronize, args.min_time)
                host = host_time(call, torch.cuda.synchronize)
                row = dict(algo=algo, model=args.model, precision='float', instances=b, out_layout=layout,
                           cxx_strategy=strategy, py_strategy=e.strategy, cxx_seconds_per_call='%.6g' % cxx,
                           py_seconds_per_call='%.6g' % py, host_seconds_per_call='%.6g' % host,
                           overhead_us='%.3f' % ((py - cxx) * 1e6), device=torch.cuda.get_device_name(),
                           torch=torch.__version__, scandyn=sd.__version__)
                rows.append(row)
                print(','.join(str(v) for v in row.values()), flush=True)
            del S, outs, out, e, ins
            torch.cuda.empty_cache()
    with open(args.out, 'w', newline='') as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print('wrote', args.out)


if __name__ == '__main__':
    main()
