#!/usr/bin/env python3
"""The GPU-vs-CPU shape sweep table of docs/benchmarks.md, from bench_cuda_sweep's JSON.

Pairs each GPU row (backend cuda) with the CPU row of the same computation,
precision, model and instance count (backend openmp or cpu-threads) and writes a
Markdown table between the markers <!-- sweep-table --> and <!-- /sweep-table -->
of the document. Columns: computation, model, links, instances, precision, the
GPU's strategy and time per call, the CPU's, the speed-up (CPU time / GPU time),
and both max relative errors against the double serial reference.

Usage: sweep_table.py --json bench/results/raw/h100-bench_cuda_sweep.json
                      [--doc docs/benchmarks.md]
"""
import argparse
import json
import os
import re
import sys

UNIT = {'ns': 1e-9, 'us': 1e-6, 'ms': 1e-3, 's': 1.0}
BEGIN, END = '<!-- sweep-table -->', '<!-- /sweep-table -->'


def fmt_time(s):
    if s < 1e-3:
        return '%.1f us' % (s * 1e6)
    if s < 1:
        return '%.2f ms' % (s * 1e3)
    return '%.2f s' % s


def rows(path):
    with open(path) as fh:
        doc = json.load(fh)
    out = {}
    for b in doc['benchmarks']:
        if b.get('run_type') == 'aggregate':
            continue
        parts = b.get('run_name', b['name']).split('/')
        algo_strategy, precision, model, backend = parts[0], parts[1], parts[2], parts[3]
        algo, _, strategy = algo_strategy.partition('_')
        key = (algo, precision, model, int(b['instances']))
        side = 'gpu' if backend == 'cuda' else 'cpu'
        out.setdefault(key, {})[side] = {
            'strategy': strategy, 'backend': backend, 'links': int(b['links']),
            'seconds': b['real_time'] * UNIT[b.get('time_unit', 'ns')],
            'err': float(b.get('max_rel_err', 0.0)),
            'error': b.get('error_occurred', False),
        }
    return out


def table(data):
    lines = ['| computation | model | links | instances | precision | GPU (strategy) | CPU, 16 threads (strategy) '
             '| speed-up | GPU max err | CPU max err |',
             '|---|---|---:|---:|---|---|---|---:|---:|---:|']
    order = sorted(data, key=lambda k: (k[0] != 'id', k[1], k[3] == 1, next(iter(data[k].values()))['links'], k[3]))
    for key in order:
        algo, precision, model, instances = key
        g, c = data[key].get('gpu'), data[key].get('cpu')
        if not g:
            continue
        links = g['links']
        name = 'inverse dynamics' if algo == 'id' else 'forward dynamics (JSI)'
        gpu = '%s (%s)' % (fmt_time(g['seconds']), g['strategy'])
        cpu = '%s (%s, %s)' % (fmt_time(c['seconds']), c['strategy'], c['backend']) if c else 'n/a'
        ratio = '%.0fx' % (c['seconds'] / g['seconds']) if c else 'n/a'
        lines.append('| %s | %s | %d | %d | %s | %s | %s | %s | %.2g | %s |' % (
            name, model, links, instances, precision, gpu, cpu, ratio, g['err'],
            '%.2g' % c['err'] if c else 'n/a'))
    return '\n'.join(lines) + '\n'


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--json', required=True)
    ap.add_argument('--doc', default=os.path.join(os.path.dirname(__file__), '..', 'docs', 'benchmarks.md'))
    args = ap.parse_args()
    text = open(args.doc).read()
    if BEGIN not in text or END not in text:
        sys.exit('%s: no %s ... %s markers' % (args.doc, BEGIN, END))
    new = re.sub(re.escape(BEGIN) + '.*?' + re.escape(END), lambda m: BEGIN + '\n' + table(rows(args.json)) + END,
                 text, flags=re.S)
    tmp = args.doc + '.tmp'
    with open(tmp, 'w') as fh:
        fh.write(new)
    os.replace(tmp, args.doc)
    print('%s: sweep table written' % args.doc)
    return 0


if __name__ == '__main__':
    sys.exit(main())
