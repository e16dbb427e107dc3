#!/usr/bin/env python3
"""Turn Google Benchmark JSON from scandyn's bench programs into result rows.

Rows go to bench/results/<device>.csv with the columns of DESIGN.md:
  algo,strategy,backend,precision,model,links,instances,seconds_per_call,evals_per_second,max_rel_err
A row whose key (all columns up to instances) already exists is replaced, so the
file holds the newest measurement of each configuration. Benchmark names are
`<algo>_<strategy>/<precision>/<model>[/<backend>]` (backend defaults to serial); counters `links`,
`instances` and `max_rel_err` come from the program. With repetitions, the
median aggregate is used.

Usage: bench_results.py --json run.json --device cpu-amd-epyc-2c [--results-dir bench/results]
"""
import argparse
import csv
import json
import os
import sys

COLUMNS = ['algo', 'strategy', 'backend', 'precision', 'model', 'links', 'instances',
           'seconds_per_call', 'evals_per_second', 'max_rel_err']
KEY = COLUMNS[:7]
UNIT = {'ns': 1e-9, 'us': 1e-6, 'ms': 1e-3, 's': 1.0}


def rows_from_json(path):
    with open(path) as fh:
        doc = json.load(fh)
    benches = doc['benchmarks']
    has_median = any(b.get('aggregate_name') == 'median' for b in benches)
    out = []
    for b in benches:
        if has_median and b.get('aggregate_name') != 'median':
            continue
        if not has_median and b.get('run_type') == 'aggregate':
            continue
        name = b.get('run_name', b['name'])
        if b.get('error_occurred'):  # a skipped row (its reason) measures nothing
            sys.stderr.write('bench_results.py: %s: skipped: %s\n' % (name, b.get('error_message', '')))
            continue
        parts = name.split('/')
        algo_part, precision, model = parts[0], parts[1], parts[2]
        backend = parts[3] if len(parts) > 3 else 'serial'
        algo, _, strategy = algo_part.partition('_')
        if not strategy:
            raise SystemExit('%s: benchmark name %r has no strategy (<algo>_<strategy>)' % (path, name))
        seconds = b['real_time'] * UNIT[b.get('time_unit', 'ns')]
        instances = int(b.get('instances', 1))
        out.append({
            'algo': algo, 'strategy': strategy, 'backend': backend, 'precision': precision,
            'model': model, 'links': int(b['links']), 'instances': instances,
            'seconds_per_call': '%.6g' % seconds,
            'evals_per_second': '%.6g' % (instances / seconds),
            'max_rel_err': '%.3g' % float(b.get('max_rel_err', 0.0)),
        })
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--json', required=True, nargs='+')
    ap.add_argument('--device', required=True, help='file name stem, e.g. cpu-amd-epyc-2c or h100')
    ap.add_argument('--results-dir', default=os.path.join(os.path.dirname(__file__), '..', 'bench', 'results'))
    args = ap.parse_args()
    path = os.path.join(args.results_dir, args.device + '.csv')
    rows = {}
    if os.path.exists(path):
        with open(path) as fh:
            for r in csv.DictReader(fh):
                rows[tuple(r[k] for k in KEY)] = r
    new = [r for j in args.json for r in rows_from_json(j)]
    for r in new:
        rows[tuple(str(r[k]) for k in KEY)] = r
    os.makedirs(args.results_dir, exist_ok=True)
    tmp = path + '.tmp'
    with open(tmp, 'w', newline='') as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS, lineterminator='\n')
        w.writeheader()
        for k in sorted(rows, key=lambda k: (k[0], k[1], k[4], k[3], int(k[5]), int(k[6]))):
            w.writerow(rows[k])
    os.replace(tmp, path)
    print('%s: %d rows (%d new or updated)' % (path, len(rows), len(new)))
    return 0


if __name__ == '__main__':
    sys.exit(main())
