#!/usr/bin/env python3
"""Merge the CSVs of several bench/compare runs on one machine into one file.

  merge.py -o bench/results/compare-h100.csv robots.csv ropes-short.csv ropes-long.csv

Every input must have bench/compare's columns (common.COLUMNS). Rows keep their
order, file by file; a row whose key (algo, strategy, backend, precision, model,
links, instances, library) a later file has again is replaced by the later one. A note
row (a peer that failed on a model: algo and instances empty) is replaced only by a
later note row for the same library and model, so leave out a run whose notes a later
run made stale. Writes through a temporary file: the output is whole or untouched.
"""
import argparse
import csv
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import COLUMNS  # noqa: E402

KEY = ('algo', 'strategy', 'backend', 'precision', 'model', 'links', 'instances', 'library')


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('-o', '--out', required=True)
    ap.add_argument('inputs', nargs='+')
    args = ap.parse_args()
    rows = {}
    for path in args.inputs:
        with open(path, newline='') as fh:
            r = csv.DictReader(fh)
            if r.fieldnames != COLUMNS:
                sys.exit('merge.py: %s: columns %s, expected %s' % (path, r.fieldnames, COLUMNS))
            for row in r:
                rows.pop(tuple(row[k] for k in KEY), None)  # a later measurement moves to the end
                rows[tuple(row[k] for k in KEY)] = row
    tmp = args.out + '.tmp'
    with open(tmp, 'w', newline='') as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS, lineterminator='\n')
        w.writeheader()
        w.writerows(rows.values())
    os.replace(tmp, args.out)
    print('merge.py: %s: %d rows from %d files' % (args.out, len(rows), len(args.inputs)))


if __name__ == '__main__':
    main()
