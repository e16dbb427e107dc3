#!/usr/bin/env python3
"""Markdown tables of inverse dynamics on ropes: time and error per strategy.

Reads bench/results/<device>.csv (rows from bench_id_scan) and prints, for each
precision, one row per rope length with time per call and max relative error of
the serial recursion, the local-frame scan and the world-frame scan (one thread),
and the two scans on OpenMP threads. With --write FILE the tables replace the text
between the markers <!-- id-scan-table:begin --> and <!-- id-scan-table:end --> in FILE.

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


def tables(path):
    rows = {}
    with open(path) as fh:
        for r in csv.DictReader(fh):
            if r['algo'] != 'id' or not r['model'].startswith('rope:') or r['instances'] != '1':
                continue
            rows[(r['precision'], int(r['links']), r['strategy'], r['backend'])] = r
    out = []
    for prec in ('float', 'double'):
        lengths = sorted({k[1] for k in rows if k[0] == prec})
        if not lengths:
            continue
        out.append('**%s** (time per call / max relative error of tau against the double recursion)\n' % prec)
        out.append('| links | ' + ' | '.join('%s %s' % (s, b) for s, b in COLUMNS) + ' |')
        out.append('|---:|' + '---:|' * len(COLUMNS))
        for n in lengths:
            cells = []
            for s, b in COLUMNS:
                r = rows.get((prec, n, s, b))
                cells.append('%s / %.2g' % (fmt_time(r['seconds_per_call']), float(r['max_rel_err'])) if r else 'n/a')
            out.append('| %d | %s |' % (n, ' | '.join(cells)))
        out.append('')
    return '\n'.join(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--device', required=True)
    ap.add_argument('--results-dir', default=os.path.join(os.path.dirname(__file__), '..', 'bench', 'results'))
    ap.add_argument('--write')
    args = ap.parse_args()
    text = tables(os.path.join(args.results_dir, args.device + '.csv'))
    if not args.write:
        print(text)
        return 0
    with open(args.write) as fh:
        doc = fh.read()
    pat = re.compile(r'(<!-- id-scan-table:begin -->\n).*?(<!-- id-scan-table:end -->)', re.S)
    if not pat.search(doc):
        raise SystemExit('%s: markers not found' % args.write)
    doc = pat.sub(lambda m: m.group(1) + text + '\n' + m.group(2), doc)
    with open(args.write, 'w') as fh:
        fh.write(doc)
    return 0


if __name__ == '__main__':
    sys.exit(main())
