#!/usr/bin/env python3
"""Host cost of one engine call from Python, on the host: the scandyn package's engines
(backend='serial', iiwa by default, B = 1) called with out= on torch CPU tensors and on
NumPy arrays, against the extension's compute() called directly on NumPy arrays (what
the Python layer adds on top of the C++ checks and the computation). Runs anywhere (no
GPU); the CUDA path's hand-over is the same (torch tensors as to_dlpack capsules) plus
the stream look-up and the launch (bench/python/call_overhead.py measures it on a GPU).

    python3 bench/python/call_cost.py [--model iiwa] [--batch 1]

Prints, per engine, microseconds per call: the best of --repeat rounds of --number calls.
"""
import argparse
import timeit

import numpy as np

ENGINES = {'id': ('InverseDynamics', ('q', 'qd', 'qdd')), 'bias': ('BiasForces', ('q', 'qd')),
           'mass': ('MassMatrix', ('q',)), 'fd': ('ForwardDynamics', ('q', 'qd', 'tau'))}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--model', default='iiwa')
    ap.add_argument('--batch', type=int, default=1)
    ap.add_argument('--number', type=int, default=5000)
    ap.add_argument('--repeat', type=int, default=15)
    args = ap.parse_args()

    import torch
    import scandyn as sd
    torch.set_num_threads(1)
    m = sd.load_model(args.model)
    B, nv = args.batch, m.nv

    def us(f):
        return min(timeit.repeat(f, number=args.number, repeat=args.repeat)) / args.number * 1e6

    g = torch.Generator().manual_seed(1)
    arrays = {k: torch.rand(B, nv, generator=g) * 2 - 1 for k in ('q', 'qd', 'qdd', 'tau')}
    print('engine,model,instances,torch_cpu_us,numpy_us,extension_us')
    for algo, (cls, names) in ENGINES.items():
        e = getattr(sd, cls)(m, backend='serial', max_batch=B, dtype=np.float32)
        shape = (B, nv, nv) if algo == 'mass' else (B, nv)
        t_out = torch.empty(shape)
        t_in = [arrays[k] for k in names]
        n_in, n_out = [x.numpy() for x in t_in], t_out.numpy()
        ext = [*n_in, n_out] + ([] if algo == 'mass' else [None]) + ([None] if algo == 'fd' else []) + [0]
        row = (us(lambda: e(*t_in, out=t_out)), us(lambda: e(*n_in, out=n_out)), us(lambda: e._e.compute(*ext)))
        print(f'{algo},{args.model},{B},' + ','.join('%.2f' % x for x in row), flush=True)


if __name__ == '__main__':
    main()
