#!/usr/bin/env python3
"""Markdown tables of inverse dynamics on ropes: time and error per strategy.

Reads bench/results/<device>.csv (rows from bench_id_scan) and prints, for each
precision, one row per rope length with time per call and max relative error of
the serial recursion, the local-frame scan and the world-frame scan (one thread),
and the two scans on OpenMP threads; then one table for the tree models (curtains,
random trees). With --write FILE the tables replace the text between the markers
<!-- id-scan-table:begin/end --> and <!-- id-scan-trees:begin/end --> in FILE.

Usage: id_scan_table.py --device h100-host-cpu16 [--write docs/accuracy-id-scan.md]
"""
import argparse
import csv
import os
import re
import sys

COLUMNS = [('recursion', 'serial'), ('scan-local', 'serial'), ('scan-world', 'serial'),
           ('scan-local', 'openmp'), ('scan-world', 'openmp')]


def fmt_time(s):
    s = float(s)
    if s < 1e-3:
        return '%.3g us' % (s * 1e6)
    if s < 1:
        return '%.3g ms' % (s * 1e3)
    return '%.3g s' % s


def read_rows(path, keep):
    rows = {}
    with open(path) as fh:
        for r in csv.DictReader(fh):
            if r['algo'] == 'id' and r['instances'] == '1' and keep(r['model']):
                rows[(r['precision'], r['model'], r['strategy'], r['backend'])] = r
    return rows


def cell(r):
    return '%s / %.2g' % (fmt_time(r['seconds_per_call']), float(r['max_rel_err'])) if r else 'n/a'


def tree_tables(path):
    """One table: the tree models (curtains, random trees), both precisions."""
    rows = read_rows(path, lambda m: m.startswith('curtain:') or m.startswith('tree:'))
    models = sorted({k[1] for k in rows}, key=lambda m: (m.split(':')[0], int(m.split(':')[1])))
    cols = [c for c in COLUMNS if c != ('scan-world', 'serial')]
    out = ['| model | precision | ' + ' | '.join('%s %s' % c for c in cols) + ' |',
           '|---|---|' + '---:|' * len(cols)]
    for m in models:
        for prec in ('float', 'double'):
            out.append('| %s | %s | %s |' % (m, prec, ' | '.join(cell(rows.get((prec, m) + c)) for c in cols)))
    return '\n'.join(out) + '\n'


def tables(path):
    raw = read_rows(path, lambda m: m.startswith('rope:'))
    rows = {(k[0], int(k[1].split(':')[1]), k[2], k[3]): r for k, r in raw.items()}
    out = []
    for prec in ('float', 'double'):
        lengths = sorted({k[1] for k in rows if k[0] == prec})
        if not lengths:
            continue
        out.append('**%s** (time per call / max relative error of tau against the double recursion)\n' % prec)
        out.append('| links | ' + ' | '.join('%s %s' % (s, b) for s, b in COLUMNS) + ' |')
        out.append('|---:|' + '---:|' * len(COLUMNS))
        for n in lengths:
            cells = [cell(rows.get((prec, n, s, b))) for s, b in COLUMNS]
            out.append('| %d | %s |' % (n, ' | '.join(cells)))
        out.append('')
    return '\n'.join(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--device', required=True)
    ap.add_argument('--results-dir', default=os.path.join(os.path.dirname(__file__), '..', 'bench', 'results'))
    ap.add_argument('--write')
    args = ap.parse_args()
    path = os.path.join(args.results_dir, args.device + '.csv')
    parts = {'id-scan-table': tables(path), 'id-scan-trees': tree_tables(path)}
    if not args.write:
        print('\n'.join(parts.values()))
        return 0
    with open(args.write) as fh:
        doc = fh.read()
    for name, text in parts.items():
        pat = re.compile(r'(<!-- %s:begin -->\n).*?(<!-- %s:end -->)' % (name, name), re.S)
        if not pat.search(doc):
            raise SystemExit('%s: markers for %s not found' % (args.write, name))
        doc = pat.sub(lambda m: m.group(1) + text + '\n' + m.group(2), doc)
    with open(args.write, 'w') as fh:
        fh.write(doc)
    return 0


if __name__ == '__main__':
    sys.exit(main())
